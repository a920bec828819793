"""The simulated bench in bench time (lockstep clock): the same scenario and seed record the same
data at any speed and host load, every device is sampled at its real rate, and the scenario's own
bias terms fitted on one live run reach the noise floor on another.

These runs go through the real ``bench run --sim`` command in subprocesses (simulators on their real
transports, drivers, engine, SQLite); the CPU hogs are plain busy loops, killed at the end."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from bench.storage import open_database
from bench.storage.export import run_dataset

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT))
SHORT = ["start_c=30", "soak_h=0.05", "warmup_min=5", "rate_c_per_min=1", "end_c=22", "final_hold_min=5"]


def _bench(args: list[str], tmp: Path, timeout_s: float = 600) -> str:
    p = subprocess.run([sys.executable, "-m", "bench.cli", *args], cwd=tmp, env=ENV, capture_output=True,
                       text=True, timeout=timeout_s)
    assert p.returncode == 0, (args, p.stdout[-2000:], p.stderr[-3000:])
    return p.stdout


def _run(tmp: Path, name: str, speed: str, seed: int, params: list[str]) -> tuple[str, int]:
    url = f"sqlite:///{tmp / (name + '.sqlite')}"
    args = ["run", "thermal_ramp", "--gyro", "L1", "--sim", "--speed", speed, "--seed", str(seed),
            "--json", "--no-progress", "--db", url]
    for p in params:
        args += ["--param", p]
    doc = json.loads(_bench(args, tmp).strip().splitlines()[-1])
    assert doc["status"] == "completed", doc
    return url, int(doc["run_id"])


class _Hogs:
    """Two CPU-bound processes beside the test (a loaded 2-core machine)."""

    def __enter__(self):
        self.procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
        return self

    def __exit__(self, *exc):
        for p in self.procs:
            p.kill()
            p.wait(10)


def test_same_seed_same_csv_at_x3600_under_load_and_at_max(tmp_path):
    with _Hogs():
        url_a, rid_a = _run(tmp_path, "loaded", "3600", 5, SHORT)
    url_b, rid_b = _run(tmp_path, "max", "max", 5, SHORT)
    csv = []
    for url, rid, name in ((url_a, rid_a, "a.csv"), (url_b, rid_b, "b.csv")):
        _bench(["export", str(rid), "--format", "csv", "-o", str(tmp_path / name), "--db", url], tmp_path)
        csv.append((tmp_path / name).read_text().splitlines())
    assert len(csv[0]) > 800
    diff = [(i, a, b) for i, (a, b) in enumerate(zip(*csv)) if a != b]
    assert len(csv[0]) == len(csv[1]) and not diff, diff[:3]

    # and every device at its real rate, in bench seconds
    show = json.loads(_bench(["runs", "show", str(rid_a), "--json", "--db", url_a], tmp_path))
    sampling = show["sampling"]
    assert sampling["probes"]["readings"] > 100 and sampling["probes"]["max_interval_s"] <= 2.0
    for name in ("t1", "t2", "t3", "t4"):
        assert sampling["probes"]["per_probe"][name]["max_interval_s"] <= 2.0
    assert sampling["chamber"]["max_interval_s"] <= 5.0
    assert sampling["psu"]["max_interval_s"] <= 10.0
    assert sampling["turntable"]["max_interval_s"] <= 10.0
    assert sampling["gyro"]["median_interval_s"] == pytest.approx(1.0)
    assert sampling["gyro"]["max_interval_s"] <= 1.0 + 1e-6


def test_true_bias_terms_fitted_on_one_live_run_reach_the_noise_floor_on_another(tmp_path):
    from bench.fit.closeloop import close_loop, public

    declared = "t1 + t1^2 + t1^3 + (t1-t3) + dt1"      # the default scenario's own bias form for x
    train = ["start_c=40", "soak_h=0.3", "warmup_min=10", "rate_c_per_min=1", "end_c=0", "final_hold_min=20"]
    held_out = ["start_c=35", "soak_h=0.3", "warmup_min=10", "rate_c_per_min=0.8", "end_c=5", "final_hold_min=20"]
    url_t, rid_t = _run(tmp_path, "train", "max", 21, train)
    url_v, rid_v = _run(tmp_path, "validate", "max", 22, held_out)
    ds_t = run_dataset(rid_t, open_database(url_t))
    ds_v = run_dataset(rid_v, open_database(url_v))
    ch = public(close_loop(ds_t, ds_v, declared, channels=["x"]))["channels"]["x"]
    std100, floor = ch["before"]["validation_std100_dph"], ch["noise_floor_dph"]
    print(f"validation std of 100-s means {std100:.4f} deg/h, noise floor {floor:.4f} deg/h, "
          f"ratio {std100 / floor:.3f} ({len(ds_t)} / {len(ds_v)} rows)")
    assert std100 <= 1.15 * floor, (std100, floor, ch["findings"])
