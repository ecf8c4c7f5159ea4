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


def test_the_full_turn_cloud_takes_the_paths_a_big_scan_takes(tmp_path):
    """The warm-up's LAZ cloud must reach the kernels a 2 M-point full-turn scan reaches: over
    200 k points (the step estimate's window subset) and no empty 0.01 deg of azimuth (the dense
    full circle's seam search)."""
    import laspy
    import numpy as np

    from forestmap_assets.io._projection_kernels import azimuth_bins

    camp = warm_kernels.full_turn_campaign(tmp_path)
    las = laspy.read(str(camp / "A.laz"))
    az = np.degrees(np.arctan2(np.asarray(las.y), np.asarray(las.x)))
    assert az.size > 200_000
    assert (azimuth_bins(az, 1, 36_000, 0.01) > 0).all()


def test_the_fine_ply_clouds_take_the_paths_foreign_scans_take(tmp_path):
    """The warm-up's PLY clouds are written as Sylva's simulator (float64 coordinates) and the
    renders of a registered cloud (float32, RGB) write theirs, without intensity, and their rows
    are fine enough that the segments see every second row (the kernels then get writable
    copies): the argument types a first run on such scans would otherwise compile."""
    from forestmap_assets.assets.ingest import read_campaign_scan
    from forestmap_assets.core.features.segments import feature_scan_lines
    from forestmap_assets.io.campaign import load_campaign

    camp = load_campaign(warm_kernels.fine_ply_campaign(tmp_path))
    for sid, coord in (("D", "double"), ("F", "float")):
        head = camp.scan(sid).path.read_bytes()[:300].decode("ascii", "replace")
        assert f"property {coord} x" in head and "intensity" not in head
        assert ("red" in head) == (sid == "F")
        image = read_campaign_scan(camp, sid)
        lines = feature_scan_lines(image, camp.params.segmentation.min_line_step_deg)
        assert lines.shape[0] <= (image.shape[0] + 1) // 2  # every second row or fewer
