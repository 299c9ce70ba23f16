"""`python -m jaxcon bench --speed-vs-error --small`: files written, every value finite, every solver in the table."""
import csv
import json
import math
import os

from jaxcon.bench.speed_vs_error import SOLVERS
from jaxcon.bench.cli import main


def _finite_numbers(row):
    return all(math.isfinite(v) for v in row.values() if isinstance(v, float))


def test_speed_vs_error_small(tmp_path):
    out = tmp_path / "sve"
    assert main(["bench", "--speed-vs-error", "--small", "--out-dir", str(out)]) == 0
    for name in ("speed_vs_error.json", "speed_vs_error.csv"):
        assert (out / name).stat().st_size > 0
    res = json.loads((out / "speed_vs_error.json").read_text())
    try:
        import matplotlib  # noqa: F401
        for p in res["plots"]:
            assert os.path.getsize(p) > 0
        assert len(res["plots"]) == len(res["scenes"])
    except ImportError:
        assert res["plots"] == []
    # every point: finite cost, compile time, error and stretch
    assert res["points"] and all(_finite_numbers(r) for r in res["points"])
    assert all(r["cost_s_per_sim_s"] > 0 and r["error"] >= 0 for r in res["points"])
    assert {r["solver"] for r in res["points"]} == set(SOLVERS)
    assert all(_finite_numbers(r) for r in res["tradeoff"] + res["scaling"])
    assert all(math.isfinite(v) for v in res["scaling_exponent"].values())
    assert all(math.isfinite(r["energy_drift"]) for r in res["drift"])
    assert all(0 <= r["max_support_force_error_rel"] < 1 for r in res["xpbd_paper"]["rows"])
    # the printed method table has one row per solver
    assert res["table_solvers"] == list(SOLVERS)
    for s in SOLVERS:
        assert f"| {s} |" in res["table"]
    with open(out / "speed_vs_error.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(res["points"]) + len(res["tradeoff"]) + len(res["mujoco"])
    # MuJoCo reference rows exist only where mujoco is installed; when they do, the mild pendulum's are finite
    # and as accurate as a first-order (Euler) or fourth-order (RK4) integrator should be at these steps
    for r in res["mujoco"]:
        if r["scene"] == "double_pendulum_mild":
            assert r["error"] < (1e-2 if r["integrator"] == "Euler" else 1e-4), r
    assert all(math.isfinite(float(r["error"])) for r in rows)
