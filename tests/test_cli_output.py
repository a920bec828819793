"""What the engineer sees from the command line: ``--db`` on every command that touches the database,
``--json -`` printing exactly one JSON object on stdout (human lines and progress on stderr), each long
step announced with its duration, numbers with units and a few significant digits, and output files
created with the user's umask."""
from __future__ import annotations

import json
import os
import re
import stat

import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.fit.csvio import write_csv
from tests.synth import TRAIN_PROFILE, VALIDATE_PROFILE, make_run

DB_COMMANDS = [["run"], ["resume"], ["runs", "list"], ["runs", "show"], ["export"], ["import"], ["fit"],
               ["close-loop"], ["coefficients"], ["serve"], ["worker"]]
LONG_NUMBER = re.compile(r"\d\.\d{7,}")         # 16-digit floats are what the old output printed


def _cli(args, **kw):
    res = CliRunner().invoke(app, [str(a) for a in args], catch_exceptions=False, **kw)
    return res.exit_code, res.stdout, res.stderr


@pytest.mark.parametrize("command", DB_COMMANDS, ids=" ".join)
def test_every_database_command_has_db(command):
    code, out, _ = _cli(command + ["--help"], env={"COLUMNS": "200", "TERMINAL_WIDTH": "200"})
    assert code == 0
    assert re.search(r"--db\s", out), out


def test_every_option_and_argument_says_what_it_is():
    import typer

    def commands(cmd, path):
        if hasattr(cmd, "commands"):
            for name, sub in cmd.commands.items():
                yield from commands(sub, path + [name])
        else:
            yield path, cmd

    bare = [f"bench {' '.join(path)} {param.name}" for path, cmd in commands(typer.main.get_command(app), [])
            for param in cmd.params if not (getattr(param, "help", None) or "").strip()]
    assert not bare, bare


def _unopenable(tmp) -> str:
    return f"sqlite:///{tmp / 'missing-dir' / 'nowhere.sqlite'}"


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    """Two runs imported with ``--db`` into a fresh SQLite file, while $BENCH_DATABASE_URL names a database
    that cannot be opened: anything that ignored ``--db`` would fail.  Imported once for the module: the
    tests only read them (``fit`` and ``close-loop`` store nothing)."""
    tmp = tmp_path_factory.mktemp("cli-output")
    url = f"sqlite:///{tmp / 'bench.sqlite'}"
    ids = []
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("BENCH_DATABASE_URL", _unopenable(tmp))
        for profile, seed, name in ((TRAIN_PROFILE, 1, "train.csv"), (VALIDATE_PROFILE, 2, "val.csv")):
            ds, _ = make_run(profile, {"rate": 0.08}, seed=seed)
            write_csv(ds, tmp / name)
            code, out, err = _cli(["import", tmp / name, "--gyro", "CLI-1", "--db", url])
            assert code == 0, err
            ids.append(int(re.match(r"run (\d+):", out).group(1)))
            assert re.search(r"import\b.*\b\d+/", err), err       # the streamed import's progress, on stderr
    return url, ids


@pytest.fixture()
def stored(imported, tmp_path, monkeypatch):
    """The imported runs, with $BENCH_DATABASE_URL again naming a database that cannot be opened."""
    monkeypatch.setenv("BENCH_DATABASE_URL", _unopenable(tmp_path))
    return imported


def test_fit_and_close_loop_on_runs_of_db_print_one_json_object_and_progress(stored):
    url, (train, val) = stored
    code, out, err = _cli(["fit", "static", train, val, "--json", "-", "--db", url])
    assert code == 0, err
    doc = json.loads(out)                                   # the whole of stdout is one JSON object
    assert doc["train_source"] == str(train) and set(doc["channels"]) == {"x"}   # the files have gyro_x only
    assert f"loading the training data (run {train}): done in " in err
    assert re.search(r"fitting static on channel x: done in \d", err), err
    line = next(ln for ln in err.splitlines() if ln.startswith("x (probe t1): "))
    assert re.fullmatch(r"x \(probe t1\): training RMS \S+ deg/h, std of 100-s means \S+ deg/h; "
                        r"validation RMS \S+ deg/h, std of 100-s means \S+ deg/h", line), line
    assert not LONG_NUMBER.search(err), err

    code, out, err = _cli(["close-loop", train, val, "--model", "static", "--json", "-", "--db", url, "--channel", "x"])
    assert code == 0, err
    doc = json.loads(out)
    assert doc["channels"]["x"]["verdict"] == "explained"
    assert re.search(r"close the loop on channel x: done in \d", err), err
    summary = next(ln for ln in err.splitlines() if ln.startswith("x: "))
    assert re.fullmatch(r"x: explained; validation std of 100-s means \d\S* deg/h -> \d\S* deg/h "
                        r"\(noise floor \d\S* deg/h\); added: .+", summary), summary
    assert not LONG_NUMBER.search(summary)

    code, out, err = _cli(["coefficients", "CLI-1", "--db", url])   # the gyro exists there, with no fit
    assert code == 1 and "CLI-1" in err and "cannot open database" not in err, err


def test_summary_goes_to_stdout_when_the_json_goes_to_a_file(tmp_path):
    train, _ = make_run(TRAIN_PROFILE[:5], {}, seed=3)
    write_csv(train, tmp_path / "train.csv")
    code, out, err = _cli(["fit", "static", tmp_path / "train.csv", "--json", tmp_path / "fit.json"])
    assert code == 0, err
    assert out.startswith("x (probe t1): training RMS ") and "deg/h" in out
    assert "fitting static on channel x" in err and "fitting" not in out


def test_output_files_follow_the_umask(stored, tmp_path):
    url, (train, _val) = stored
    old = os.umask(0o027)
    try:
        code, _, err = _cli(["export", train, "--format", "csv", "-o", tmp_path / "run.csv", "--db", url])
        assert code == 0, err
        assert f"reading run {train}: done in " in err
        code, _, err = _cli(["fit", "static", train, "--json", tmp_path / "fit.json", "--db", url])
        assert code == 0, err
    finally:
        os.umask(old)
    for name in ("run.csv", "fit.json"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o640, name
