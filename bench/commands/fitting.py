"""``bench fit`` and ``bench close-loop``.

Both print each long step on stderr as it runs (loading the data, fitting or analysing each channel,
writing the report) and how long it took; stdout holds only the result: the JSON document with
``--json -``, else one summary line per channel with units.
"""
from __future__ import annotations

from typing import Any, Optional

import typer

from bench.commands.common import (clean_floats, db_option, guarded, load_dataset, quantity, step,
                                   write_json)


# the arguments and options both commands take (one declaration each)
TRAIN_ARG = typer.Argument(..., help="training data: measured-data CSV or run ID")
HTML_OPT = typer.Option(None, "--html", help="write the HTML report here")
CHANNEL_OPT = typer.Option(None, "--channel", help="channel(s) (default: all)")
LATITUDE_OPT = typer.Option(None, "--latitude", help="latitude in degrees (Earth-rate removal)")


def register(app: typer.Typer) -> None:
    app.command("fit")(fit_command)
    app.command("close-loop")(close_loop_command)


def _load(kind: str, spec: str, db_url: str | None):
    what = f"run {spec}" if spec.isdigit() else spec
    with step(f"loading the {kind} data ({what})"):
        return load_dataset(spec, db_url)


def _summary(line: str, json_out: str) -> None:
    """A human line: stdout, or stderr when stdout carries the JSON document."""
    typer.echo(line, err=json_out == "-")


@guarded
def fit_command(
    model: str = typer.Argument(..., help="static, dynamic, patent37, hrg, hrg_pso, hrg_reverse, fog_stepwise, "
                                          "fog_delaunay, or a formula like 't1 + t1^2 + dt1'"),
    train: str = TRAIN_ARG,
    validate: Optional[str] = typer.Argument(None, help="validation data: measured-data CSV or run ID"),
    json_out: str = typer.Option(..., "--json", help="write the result JSON here ('-' = stdout)"),
    html_out: Optional[str] = HTML_OPT,
    channel: Optional[list[str]] = CHANNEL_OPT,
    latitude: Optional[float] = LATITUDE_OPT,
    db_url: Optional[str] = db_option(),
) -> None:
    """Fit a temperature model and report its error on the training and validation data."""
    from bench.fit.catalog import predict
    from bench.fit.channels import fit_channels
    from bench.jsonsafe import jsonable

    train_ds = _load("training", train, db_url)
    val_ds = _load("validation", validate, db_url) if validate else None
    channels = list(channel) if channel else train_ds.gyro_channels()
    opts: dict[str, Any] = {}
    if latitude is not None:
        opts["latitude_deg"] = latitude
    doc: dict[str, Any] = {"model": model, "glitches_removed": {}, "channels": {}}
    results = []
    for ch in channels:
        with step(f"fitting {model} on channel {ch}"):
            one, res = fit_channels(model, train_ds, val_ds, [ch], opts)
        doc["model"], doc["glitches_removed"] = one["model"], one["glitches_removed"]
        doc["channels"].update(one["channels"])
        results += res
    doc = jsonable(doc)
    for r in results:
        warning = ((r.definition or {}).get("earth_rate") or {}).get("warning")
        if warning:
            typer.secho(f"warning: {r.channel}: {warning}", err=True, fg=typer.colors.YELLOW)
    doc["train_source"], doc["validation_source"] = train, validate
    write_json(json_out, doc)
    if html_out:
        from bench.fit.report import render_fit_report
        from bench.files import write_text_atomic

        with step(f"writing the HTML report {html_out}"):
            page = render_fit_report(results, train_ds, val_ds, predict=predict, title=f"Fit report: {model}")
            write_text_atomic(html_out, page)
    for ch, entry in doc["channels"].items():
        tr, va = entry.get("train", {}), entry.get("validation")
        probe = (entry.get("definition") or {}).get("probe")
        label = f"{ch} (probe {probe})" if probe else ch
        line = (f"{label}: training RMS {quantity(tr.get('rms_dph'), 'deg/h')}, "
                f"std of 100-s means {quantity(tr.get('std100_dph'), 'deg/h')}")
        if va:
            line += (f"; validation RMS {quantity(va.get('rms_dph'), 'deg/h')}, "
                     f"std of 100-s means {quantity(va.get('std100_dph'), 'deg/h')}")
        if "max_abs_error_c" in entry:
            line += f"; max |error| {quantity(entry['max_abs_error_c'], '°C')}"
        _summary(line, json_out)
    _glitch_summary(doc.get("glitches_removed") or {}, json_out)


@guarded
def close_loop_command(
    train: str = TRAIN_ARG,
    validate: str = typer.Argument(..., help="held-out validation data: measured-data CSV or run ID"),
    model: str = typer.Option(..., "--model", help="declared model: a linear named model or a formula"),
    json_out: str = typer.Option(..., "--json", help="write the report JSON here ('-' = stdout)"),
    html_out: Optional[str] = HTML_OPT,
    channel: Optional[list[str]] = CHANNEL_OPT,
    latitude: Optional[float] = LATITUDE_OPT,
    db_url: Optional[str] = db_option(),
) -> None:
    """Find what the declared model misses, add the effects that help on the held-out run, report."""
    from bench.fit.closeloop import close_loop, public, unmeasured_channel
    from bench.fit.closeloop_report import render_close_loop_report

    train_ds, val_ds = _load("training", train, db_url), _load("held-out", validate, db_url)
    report: dict[str, Any] | None = None
    channels = list(channel) if channel else train_ds.gyro_channels()
    # channels not asked for by name that a run never measured are left out (and named), as close_loop does
    skipped = {} if channel else {ch: why for ch in channels if (why := unmeasured_channel(train_ds, val_ds, ch))}
    # (when every channel was skipped, the first is tried anyway: close_loop raises the error naming it)
    for ch in [c for c in channels if c not in skipped] or channels:
        with step(f"close the loop on channel {ch}"):
            one = close_loop(train_ds, val_ds, model, channels=[ch], latitude_deg=latitude)
        if report is None:
            report = one
        else:
            report["channels"].update(one["channels"])
    if skipped:
        report["channels_not_analysed"] = skipped
    doc = clean_floats(public(report))
    doc["train_source"], doc["validation_source"] = train, validate
    write_json(json_out, doc)
    if html_out:
        from bench.files import write_text_atomic

        with step(f"writing the HTML report {html_out}"):
            write_text_atomic(html_out, render_close_loop_report(report, train_ds, val_ds))
    for ch, r in doc["channels"].items():
        _summary(f"{ch}: {str(r['verdict']).replace('_', ' ')}; validation std of 100-s means "
                 f"{quantity(r['before']['validation_std100_dph'], 'deg/h')} -> "
                 f"{quantity(r['after']['validation_std100_dph'], 'deg/h')} (noise floor "
                 f"{quantity(r.get('noise_floor_dph'), 'deg/h')}); added: "
                 f"{', '.join(e['kind'] for e in r['effects_added']) or 'nothing'}", json_out)
    for ch, why in skipped.items():
        _summary(f"{ch}: not analysed: {why}", json_out)
    _glitch_summary(doc.get("glitches_removed") or {}, json_out)


def _glitch_summary(removed: dict[str, dict[str, Any]], json_out: str) -> None:
    """One line naming the isolated glitches set missing before the analysis, when there were any."""
    parts = [f"{run} {col} {info['samples']} (first at t = {info['time_s'][0]:g} s)"
             for run, cols in removed.items() for col, info in cols.items()]
    if parts:
        _summary("glitches set missing (isolated readings far off the signal's course): " + "; ".join(parts), json_out)
