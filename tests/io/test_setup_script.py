"""scripts/setup.sh and its system-library check (scripts/system_libs.sh), run with bash.

``ldconfig -p | grep -q NAME`` under ``set -o pipefail`` reports a present library as missing
when the cache is long: grep stops at the first match, ldconfig dies of SIGPIPE (status 141)
and the pipeline fails. These tests feed a fake ``ldconfig`` with a long listing and check that
the library is found, that a missing one is reported, and that set-up as a normal user without
sudo does not touch apt when everything is there. The full set-up runs on a copy of the scripts
with fake ``python3`` / ``apt-get`` / ``sudo`` / ``id``, so nothing is installed.
"""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SCRIPTS = REPO / "scripts"
BASH = shutil.which("bash")
# what setup.sh and the fakes below call; everything else (sudo, apt-get, ldconfig) is left out
TOOLS = ("dirname", "grep", "cat", "env", "mkdir", "chmod")

pytestmark = pytest.mark.skipif(BASH is None, reason="needs bash")

FAKE_LIB = "libforestmap-fake.so.1"


def _script(path: Path, text: str) -> Path:
    path.write_text(text)
    path.chmod(path.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    return path


def _listing(path: Path, first: list[str], lines: int = 40_000) -> Path:
    """An ``ldconfig -p`` listing: the given libraries first, then many others (~2.5 MB, far
    more than a pipe holds, so a reader that stops early leaves the writer to SIGPIPE)."""
    rows = [f"{lines + len(first)} libs found in cache `/etc/ld.so.cache'"]
    rows += [f"\t{name} (libc6,x86-64) => /usr/lib/x86_64-linux-gnu/{name}" for name in first]
    rows += [f"\tlibother{i}.so.{i % 7} (libc6,x86-64) => /usr/lib/libother{i}.so" for i in range(lines)]
    path.write_text("\n".join(rows) + "\n")
    return path


@pytest.fixture
def bin_dir(tmp_path) -> Path:
    """A PATH folder with only the basic tools: no ldconfig, sudo or apt-get unless a test adds
    a fake one."""
    folder = tmp_path / "bin"
    folder.mkdir()
    for tool in TOOLS:
        found = shutil.which(tool)
        assert found, tool
        (folder / tool).symlink_to(found)
    return folder


def fake_ldconfig(bin_dir: Path, tmp_path: Path, libraries: list[str]) -> None:
    listing = _listing(tmp_path / "ld.so.cache.txt", libraries)
    _script(bin_dir / "ldconfig", f"#!{BASH}\nexec {shutil.which('cat')} {listing}\n")


def bash(code: str, path: Path | None = None, **env) -> subprocess.CompletedProcess:
    """Run ``code`` with bash under ``set -euo pipefail`` after sourcing system_libs.sh."""
    environ = {**os.environ, **env}
    if path is not None:
        environ["PATH"] = str(path)
    return subprocess.run(
        [BASH, "-c", f"set -euo pipefail; source {SCRIPTS / 'system_libs.sh'}; {code}"],
        capture_output=True, text=True, env=environ, timeout=30,
    )


def test_the_old_check_loses_the_race_with_this_listing(bin_dir, tmp_path):
    """The fake reproduces the bug: the old ``have`` misses a library listed first."""
    fake_ldconfig(bin_dir, tmp_path, [FAKE_LIB])
    old = 'have() { ldconfig -p 2>/dev/null | grep -q "$1"; }; have ' + FAKE_LIB
    assert bash(old, path=bin_dir).returncode != 0


def test_library_in_a_long_ldconfig_listing_is_found_under_pipefail(bin_dir, tmp_path):
    fake_ldconfig(bin_dir, tmp_path, [FAKE_LIB])
    res = bash(f"where_lib {FAKE_LIB}; have_lib {FAKE_LIB} && echo yes", path=bin_dir)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["ldconfig", "yes"]


def test_libc_is_found_on_this_machine():
    res = bash("have_lib libc.so.6 && echo found")
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "found"


def test_a_missing_library_is_reported_missing(bin_dir, tmp_path):
    fake_ldconfig(bin_dir, tmp_path, [FAKE_LIB])
    res = bash("if have_lib libnot-there-at-all.so.9; then echo found; else echo missing; fi",
               path=bin_dir)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "missing"


def test_a_library_outside_the_ldconfig_cache_is_found_in_ld_library_path(bin_dir, tmp_path):
    fake_ldconfig(bin_dir, tmp_path, [])
    lib = tmp_path / "lib"
    lib.mkdir()
    (lib / FAKE_LIB).write_bytes(b"")
    res = bash(f"where_lib {FAKE_LIB}", path=bin_dir, LD_LIBRARY_PATH=f"/nonexistent:{lib}")
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == str(lib / FAKE_LIB)


def test_check_prints_one_line_per_library_and_installs_nothing(bin_dir, tmp_path):
    fake_ldconfig(bin_dir, tmp_path, ["libusb-1.0.so.0"])  # libEGL.so.1 not listed
    log = tmp_path / "apt.log"
    _script(bin_dir / "apt-get", f"#!{BASH}\necho \"apt-get $*\" >> {log}\n")
    _script(bin_dir / "sudo", f"#!{BASH}\necho \"sudo $*\" >> {log}\n")
    env = {**os.environ, "PATH": str(bin_dir), "LD_LIBRARY_PATH": ""}
    res = subprocess.run([BASH, str(SCRIPTS / "setup.sh"), "--check"], capture_output=True,
                         text=True, env=env, timeout=30)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert lines[0] == "libusb-1.0.so.0 found (ldconfig)"
    # on this machine libEGL may sit in a library folder; in the listing it does not
    assert lines[1].startswith("libEGL.so.1 ")
    assert len(lines) == 2
    assert not log.exists()


# --- the whole set-up, on a copy of the scripts, with fakes for everything it would install ---


@pytest.fixture
def repo_copy(tmp_path) -> Path:
    root = tmp_path / "repo"
    (root / "scripts").mkdir(parents=True)
    for name in ("setup.sh", "system_libs.sh"):
        shutil.copy(SCRIPTS / name, root / "scripts" / name)
    return root


def without_libusb(repo_copy: Path) -> None:
    """Make the copy look for a libusb that no machine has (this one has the real one in its
    library folders, where the check also looks)."""
    libs = repo_copy / "scripts" / "system_libs.sh"
    text = libs.read_text()
    assert "'libusb-1.0.so.0|" in text
    libs.write_text(text.replace("'libusb-1.0.so.0|", "'libusb-not-on-any-machine.so.0|"))


def setup_run(repo_copy: Path, bin_dir: Path, tmp_path: Path, *, uid: int, sudo: bool):
    """Run the copied setup.sh as user ``uid``, with or without a (fake) sudo; returns the
    result and the log of every apt-get / sudo / python call."""
    log = tmp_path / "calls.log"
    _script(bin_dir / "id", f"#!{BASH}\necho {uid}\n")
    _script(bin_dir / "apt-get", f"#!{BASH}\necho \"apt-get $*\" >> {log}\n")
    if sudo:
        _script(bin_dir / "sudo", f"#!{BASH}\necho \"sudo $*\" >> {log}\nexec \"$@\"\n")
    venv_python = _script(tmp_path / "venv_python", f"#!{BASH}\necho \"python $*\" >> {log}\n")
    _script(bin_dir / "python3", f"#!{BASH}\necho \"python3 $*\" >> {log}\n"
            f"mkdir -p \"$3/bin\" && cat {venv_python} > \"$3/bin/python\" && chmod +x \"$3/bin/python\"\n")
    env = {**os.environ, "PATH": str(bin_dir), "LD_LIBRARY_PATH": ""}
    res = subprocess.run([BASH, str(repo_copy / "scripts" / "setup.sh")], capture_output=True,
                         text=True, env=env, timeout=30)
    calls = log.read_text().splitlines() if log.exists() else []
    return res, calls


def test_everything_present_as_a_user_without_sudo_does_not_try_apt(repo_copy, bin_dir, tmp_path):
    fake_ldconfig(bin_dir, tmp_path, ["libusb-1.0.so.0", "libEGL.so.1"])
    res, calls = setup_run(repo_copy, bin_dir, tmp_path, uid=1000, sudo=False)
    assert res.returncode == 0, res.stderr
    assert not [c for c in calls if c.startswith(("apt-get", "sudo"))]
    assert calls == [
        "python3 -m venv .venv",
        "python -m pip install -q --upgrade pip",
        'python -m pip install -q -e .[dev]',
        "python -m forestmap_assets.warm_kernels --check",  # the (fake) kernel cache is current
    ]
    # one line per thing installed: the venv, pip, forestmap; then where it went
    assert res.stdout.splitlines() == [
        f"setup: creating the virtual environment {repo_copy}/.venv",
        "setup: installing the latest pip into .venv",
        "setup: installing forestmap (editable, with its dev extra) into .venv",
        f"forestmap installed in {repo_copy}/.venv",
    ]


def test_missing_library_without_root_or_sudo_fails_clearly(repo_copy, bin_dir, tmp_path):
    fake_ldconfig(bin_dir, tmp_path, ["libEGL.so.1"])
    without_libusb(repo_copy)
    res, calls = setup_run(repo_copy, bin_dir, tmp_path, uid=1000, sudo=False)
    assert res.returncode == 1
    assert "libusb-1.0-0" in res.stderr and "neither root nor sudo" in res.stderr
    assert calls == []  # neither apt nor the venv


def test_missing_library_is_installed_through_sudo_one_line_per_package(repo_copy, bin_dir, tmp_path):
    fake_ldconfig(bin_dir, tmp_path, ["libEGL.so.1"])
    without_libusb(repo_copy)
    res, calls = setup_run(repo_copy, bin_dir, tmp_path, uid=1000, sudo=True)
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines()[0] == "setup: installing libusb-1.0-0 (apt)"
    assert "sudo apt-get update -qq" in calls
    assert "apt-get install -y -qq libusb-1.0-0" in calls
    assert "sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0" in calls
