"""Where-to-scan-next runs give way to the map's stages (issue 16; orchestration/priority.py)."""

import os
import threading

import pytest

from forestmap_assets.orchestration.priority import BACKGROUND_NICE, background

pytestmark = pytest.mark.skipif(not hasattr(os, "setpriority"), reason="no nice values here")


def _nice(tid: int = 0) -> int:
    return os.getpriority(os.PRIO_PROCESS, tid)


def test_background_lowers_every_thread_and_restores_where_allowed():
    before = _nice()
    seen = {}
    started, release = threading.Event(), threading.Event()

    def other():
        seen["tid"] = threading.get_native_id()
        started.set()
        release.wait(10)

    t = threading.Thread(target=other)
    t.start()
    started.wait(10)
    try:
        other_before = _nice(seen["tid"])
        with background():
            assert _nice() == min(before + BACKGROUND_NICE, 19)
            # Linux keeps a nice value per thread: the threads already running give way too
            assert _nice(seen["tid"]) == min(other_before + BACKGROUND_NICE, 19)
        after = _nice()
    finally:
        release.set()
        t.join()
    # put back where the system allows lowering it again (root, CAP_SYS_NICE), else it stays
    assert after == before or after == min(before + BACKGROUND_NICE, 19)


def test_background_off_changes_nothing():
    before = _nice()
    with background(False):
        assert _nice() == before
    assert _nice() == before
