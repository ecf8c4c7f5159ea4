"""``forestmap solve`` core: ``run_solve`` end to end on Table 6.6 and its input validation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from forestmap_assets.core.mapping.chaining import chain_poses
from forestmap_assets.outputs.solve import SolveInputError, run_solve, solve_observations
from forestmap_assets.params import MappingParams

TABLES = Path(__file__).parents[1] / "data" / "thesis_tables"
COLS = ["scan", "reference", "dx", "dy", "dz", "dheading_deg",
        "sd_x", "sd_y", "sd_z", "sd_heading_deg"]
POSES_HEADER = "scan,x,y,z,heading_deg,sd_x,sd_y,sd_z,sd_heading_deg,registered"
RESIDUALS_HEADER = "scan,reference,ex,ey,ez,eheading_deg,rx,ry,rz,rheading,verdict"


@pytest.fixture()
def forest_csv(tmp_path) -> Path:
    t = pd.read_csv(TABLES / "table_6_6_forest_local.csv", dtype={"scan": str, "reference": str})
    path = tmp_path / "OBSERVATIONS.csv"
    t[t["estimate"] == "cloud"][COLS].to_csv(path, index=False)
    return path


def test_run_solve_table_6_6_end_to_end(forest_csv, tmp_path):
    out = tmp_path / "out"
    poses_path, residuals_path = run_solve(forest_csv, "T,S,R,Q,O,N", out)
    assert poses_path == out / "poses.csv" and residuals_path == out / "residuals.csv"
    assert poses_path.read_text().splitlines()[0] == POSES_HEADER
    assert residuals_path.read_text().splitlines()[0] == RESIDUALS_HEADER
    assert sorted(p.name for p in out.iterdir()) == ["poses.csv", "residuals.csv"]  # no temps
    poses = pd.read_csv(poses_path, dtype={"scan": str}).set_index("scan")
    assert list(poses.index) == list("TSRQON")
    assert poses["registered"].dtype == bool and poses["registered"].all()
    assert (poses.loc["T"].drop("registered") == 0).all()
    assert poses["heading_deg"].between(-180, 180, inclusive="right").all()
    t68 = pd.read_csv(TABLES / "table_6_8_forest_phases.csv").query("phase == 5")
    want = t68.set_index("scan")
    got = poses.loc[want.index]
    np.testing.assert_allclose(got[["x", "y", "z"]], want[["x", "y", "z"]], atol=0.02)
    dh = (got["heading_deg"] - want["heading_deg"] + 180) % 360 - 180  # O: -95.24 vs 264.76
    assert np.abs(dh).max() < 0.1
    assert got.loc["O", "heading_deg"] == pytest.approx(264.76 - 360, abs=0.1)
    np.testing.assert_allclose(got["sd_x"], 0.02, atol=0.015)
    res = pd.read_csv(residuals_path, dtype={"scan": str, "reference": str})
    assert len(res) == 10 and (res["verdict"] == "ok").all()
    assert set(res.loc[res["rz"].abs() > 3, "scan"] + res.loc[res["rz"].abs() > 3, "reference"]) \
        == {"QS", "OS"}
    rt = res[(res["scan"] == "R") & (res["reference"] == "T")].iloc[0]  # projected by T: 0 deg
    assert rt["rx"] == pytest.approx(rt["ex"] / 0.08, abs=1e-4)
    assert rt["rheading"] == pytest.approx(rt["eheading_deg"] / 0.48, abs=1e-4)
    t610 = pd.read_csv(TABLES / "table_6_10_forest_residuals.csv")
    np.testing.assert_allclose(res[["ex", "ey", "ez"]].abs(), t610[["ex", "ey", "ez"]],
                               atol=0.025)


def test_default_order_is_first_appearance(forest_csv, tmp_path):
    """Reading each row's reference before its scan, Table 6.6 gives T, S, R, Q, O, N."""
    a = pd.read_csv(run_solve(forest_csv, None, tmp_path / "a")[0])
    b = pd.read_csv(run_solve(forest_csv, ["T", "S", "R", "Q", "O", "N"], tmp_path / "b")[0])
    pd.testing.assert_frame_equal(a, b)
    # a different order: another reference frame (N at the origin), same scans
    c = pd.read_csv(run_solve(forest_csv, "N,O,Q,R,S,T", tmp_path / "c")[0], dtype={"scan": str})
    assert c.iloc[0]["scan"] == "N" and c.iloc[0]["x"] == 0 and c["registered"].all()
    # distance T-N is frame independent (to the solver's linearisation differences)
    t = c.set_index("scan").loc["T", ["x", "y"]].to_numpy(dtype=float)
    n = a.set_index("scan").loc["N", ["x", "y"]].to_numpy(dtype=float)
    assert np.linalg.norm(t) == pytest.approx(np.linalg.norm(n), abs=0.05)


def test_unreached_scan_written_empty(forest_csv, tmp_path):
    text = forest_csv.read_text() + "X,Y,1,0,0,0,0.1,0.1,0.1,1\n"
    forest_csv.write_text(text)
    poses_path, residuals_path = run_solve(forest_csv, out_dir=tmp_path / "o")
    lines = {ln.split(",")[0]: ln for ln in poses_path.read_text().splitlines()[1:]}
    assert lines["X"] == "X,,,,,,,,,false" and lines["Y"] == "Y,,,,,,,,,false"
    assert lines["T"].endswith(",true")
    assert len(pd.read_csv(residuals_path)) == 10


def test_chain_method(forest_csv):
    obs = pd.read_csv(forest_csv, dtype={"scan": str, "reference": str})
    res = solve_observations(obs, list("TSRQON"), MappingParams(method="chain"))
    chained = chain_poses(obs, list("TSRQON"))
    np.testing.assert_allclose(res.poses[["x", "y", "z"]], chained[["x", "y", "z"]])
    assert res.optimal_map is None
    assert len(res.residuals) == 10
    # the chain's own links (S-T, R-S, Q-R, O-Q, N-O) have zero residual, loops do not
    r = res.residuals.set_index(res.residuals["scan"] + res.residuals["reference"])
    assert np.abs(r.loc[["ST", "RS", "QR", "OQ", "NO"], ["ex", "ey", "ez"]]).max().max() < 1e-9
    assert np.abs(r.loc[["RT", "QS", "QT", "OR", "OS"], ["ex", "ey"]]).max().max() > 0.005


def test_full_covariance_option(forest_csv):
    obs = pd.read_csv(forest_csv, dtype={"scan": str, "reference": str})
    pub = solve_observations(obs, None, MappingParams())
    full = solve_observations(obs, None, MappingParams(covariance="full"))
    # the heading-of-reference term inflates the x/y sigmas of far sub-maps
    assert (full.poses["sd_x"].iloc[1:] >= pub.poses["sd_x"].iloc[1:] - 1e-12).all()
    assert full.poses["sd_y"].iloc[-1] > pub.poses["sd_y"].iloc[-1] + 0.002
    np.testing.assert_allclose(full.poses[["x", "y"]], pub.poses[["x", "y"]], atol=0.05)


def _write(tmp_path, text: str) -> Path:
    p = tmp_path / "obs.csv"
    p.write_text(text)
    return p


GOOD_ROW = "S,T,4.43,-1.46,0.68,-38.71,0.03,0.03,0.29,0.27\n"


@pytest.mark.parametrize(
    ("body", "order", "fragments"),
    [
        ("scan,reference,dx,dy,dz,dheading_deg,sd_x,sd_y,sd_z\n" + GOOD_ROW, None,
         ["obs.csv", "missing column", "sd_heading_deg"]),
        (",".join(COLS) + "\n" + GOOD_ROW + "R,S,4.08,abc,0.14,161.3,0.04,0.03,0.15,0.24\n",
         None, ["obs.csv", "line 3", "column dy", "'abc'"]),
        (",".join(COLS) + "\n" + GOOD_ROW + "R,S,4.08,-3.69,0.14,161.3,0.04,0.03,0.15,\n",
         None, ["obs.csv", "line 3", "column sd_heading_deg"]),
        (",".join(COLS) + "\n" + GOOD_ROW + "R,S,4.08,-3.69,0.14,161.3,0.04,0,0.15,0.24\n",
         None, ["obs.csv", "line 3", "column sd_y", "positive"]),
        (",".join(COLS) + "\n" + GOOD_ROW + "R,S,4.08,-3.69,0.14,161.3,-0.1,0.1,0.15,0.24\n",
         None, ["obs.csv", "line 3", "column sd_x", "positive"]),
        (",".join(COLS) + "\n" + GOOD_ROW, "T,S,Q", ["obs.csv", "--order", "Q"]),
        (",".join(COLS) + "\n" + GOOD_ROW, "T,S,T", ["obs.csv", "--order", "more than once"]),
        (",".join(COLS) + "\n" + "S,S,1,1,1,1,1,1,1,1\n", None, ["obs.csv", "line 2", "same"]),
        (",".join(COLS) + "\n", None, ["obs.csv", "no observations"]),
    ],
)
def test_validation_errors_are_one_line(tmp_path, body, order, fragments):
    path = _write(tmp_path, body)
    with pytest.raises(SolveInputError) as exc:
        run_solve(path, order, tmp_path / "out")
    msg = str(exc.value)
    assert "\n" not in msg
    for f in fragments:
        assert f in msg, msg
    assert not (tmp_path / "out" / "poses.csv").exists()


def test_missing_file(tmp_path):
    with pytest.raises(SolveInputError, match="nope.csv: file not found"):
        run_solve(tmp_path / "nope.csv")


def test_output_replaced_atomically(forest_csv, tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / "poses.csv").write_text("stale\n")
    poses_path, _ = run_solve(forest_csv, None, out)
    assert poses_path.read_text().startswith(POSES_HEADER)
    assert not [p for p in out.iterdir() if p.suffix == ".tmp"]


def test_gauss_newton_and_iterate_options(forest_csv):
    """The (not yet parameterised) options: iterated projection and the maximum-likelihood
    Gauss-Newton map stay within a few mm / hundredths of a degree of the thesis's solve on
    Table 6.6 and keep every pair consistent; GN still returns all five phases."""
    obs = pd.read_csv(forest_csv, dtype={"scan": str, "reference": str})
    base = solve_observations(obs, None, MappingParams()).poses
    for kw in ({"iterate": True}, {"linearisation": "gauss_newton"}):
        res = solve_observations(obs, None, MappingParams(), **kw)
        np.testing.assert_allclose(res.poses[["x", "y", "z"]], base[["x", "y", "z"]], atol=0.005)
        np.testing.assert_allclose(res.poses["heading_deg"], base["heading_deg"], atol=0.05)
        assert (res.residuals["verdict"] == "ok").all()
        assert len(res.optimal_map.phases) == 5
    with pytest.raises(ValueError, match="linearisation"):
        solve_observations(obs, None, MappingParams(), linearisation="newton")
