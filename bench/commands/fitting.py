"""``bench fit`` and ``bench close-loop``."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer

from bench.commands.common import clean_floats, guarded, load_dataset, write_json


def register(app: typer.Typer) -> None:
    app.command("fit")(fit_command)
    app.command("close-loop")(close_loop_command)


@guarded
def fit_command(
    model: str = typer.Argument(..., help="static, dynamic, patent37, hrg, hrg_pso, hrg_reverse, fog_stepwise, "
                                          "fog_delaunay, or a formula like 't1 + t1^2 + dt1'"),
    train: str = typer.Argument(..., help="training data: measured-data CSV or run ID"),
    validate: Optional[str] = typer.Argument(None, help="validation data: measured-data CSV or run ID"),
    json_out: str = typer.Option(..., "--json", help="write the result JSON here ('-' = stdout)"),
    html_out: Optional[str] = typer.Option(None, "--html", help="write the HTML report here"),
    channel: Optional[list[str]] = typer.Option(None, "--channel", help="channel(s) to fit (default: all)"),
    latitude: Optional[float] = typer.Option(None, "--latitude", help="latitude in degrees (Earth-rate removal)"),
) -> None:
    """Fit a temperature model and report its error on the training and validation data."""
    from bench.fit.catalog import predict
    from bench.fit.channels import fit_channels

    train_ds = load_dataset(train)
    val_ds = load_dataset(validate) if validate else None
    channels = list(channel) if channel else train_ds.gyro_channels()
    opts: dict[str, Any] = {}
    if latitude is not None:
        opts["latitude_deg"] = latitude
    doc, results = fit_channels(model, train_ds, val_ds, channels, opts)
    for r in results:
        warning = ((r.definition or {}).get("earth_rate") or {}).get("warning")
        if warning:
            typer.secho(f"warning: {r.channel}: {warning}", err=True, fg=typer.colors.YELLOW)
    doc["train_source"], doc["validation_source"] = train, validate
    write_json(json_out, doc)
    if html_out:
        from bench.fit.report import render_fit_report

        page = render_fit_report(results, train_ds, val_ds, predict=predict, title=f"Fit report: {model}")
        Path(html_out).write_text(page)
    if json_out != "-":
        for ch, entry in doc["channels"].items():
            tr, va = entry.get("train", {}), entry.get("validation")
            probe = (entry.get("definition") or {}).get("probe")
            label = f"{ch} (probe {probe})" if probe else ch
            line = f"{label}: train rms {tr.get('rms_dph')}, std100 {tr.get('std100_dph')}"
            if va:
                line += f"; validation rms {va.get('rms_dph')}, std100 {va.get('std100_dph')}"
            typer.echo(line)


@guarded
def close_loop_command(
    train: str = typer.Argument(..., help="training data: measured-data CSV or run ID"),
    validate: str = typer.Argument(..., help="held-out validation data: measured-data CSV or run ID"),
    model: str = typer.Option(..., "--model", help="declared model: a linear named model or a formula"),
    json_out: str = typer.Option(..., "--json", help="write the report JSON here ('-' = stdout)"),
    html_out: Optional[str] = typer.Option(None, "--html", help="write the HTML report here"),
    channel: Optional[list[str]] = typer.Option(None, "--channel", help="channel(s) (default: all)"),
    latitude: Optional[float] = typer.Option(None, "--latitude", help="latitude in degrees (Earth-rate removal)"),
) -> None:
    """Find what the declared model misses, add the effects that help on the held-out run, report."""
    from bench.fit.closeloop import close_loop, public
    from bench.fit.closeloop_report import render_close_loop_report

    train_ds, val_ds = load_dataset(train), load_dataset(validate)
    report = close_loop(train_ds, val_ds, model, channels=list(channel) if channel else None, latitude_deg=latitude)
    doc = clean_floats(public(report))
    doc["train_source"], doc["validation_source"] = train, validate
    write_json(json_out, doc)
    if html_out:
        Path(html_out).write_text(render_close_loop_report(report, train_ds, val_ds))
    if json_out != "-":
        for ch, r in doc["channels"].items():
            typer.echo(f"{ch}: {r['verdict']}; validation std100 {r['before']['validation_std100_dph']:.4g} -> "
                       f"{r['after']['validation_std100_dph']:.4g} deg/h; added: "
                       f"{', '.join(e['kind'] for e in r['effects_added']) or 'nothing'}")
