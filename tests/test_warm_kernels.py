"""The kernel warm-up that scripts/setup.sh runs (issue 16): skipped while its stamp matches."""

from forestmap_assets import warm_kernels


def test_check_follows_the_stamp(tmp_path, monkeypatch):
    stamp = tmp_path / "warm_kernels.stamp"
    monkeypatch.setattr(warm_kernels, "stamp_file", lambda: stamp)
    assert warm_kernels.main(["--check"]) == 1  # never warmed
    stamp.write_text(warm_kernels.fingerprint())
    assert warm_kernels.main(["--check"]) == 0
    assert warm_kernels.main([]) == 0  # up to date: nothing compiled, nothing run
    stamp.write_text("an older kernel source")
    assert warm_kernels.main(["--check"]) == 1


def test_fingerprint_follows_the_cache_folder(monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    here = warm_kernels.fingerprint()
    monkeypatch.setenv("NUMBA_CACHE_DIR", "/elsewhere")
    assert warm_kernels.fingerprint() != here
