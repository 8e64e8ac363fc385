"""The ``blockloc`` command line: a thin typer app.

Every command body imports what it needs lazily so ``blockloc --help`` stays instant; any
BlocklocError becomes one ``error: ...`` line and exit code 2 (a traceback only with --debug).
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Optional

import typer

from blockloc import __version__

app = typer.Typer(
    name="blockloc",
    help="Localize a LiDAR + IMU robot in a large prior map, holding only the blocks it needs.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
map_app = typer.Typer(help="Build, tile, inspect and serve map stores.", no_args_is_help=True)
app.add_typer(map_app, name="map")

_state = {"debug": False}
log = logging.getLogger("blockloc")


def _version(value: bool) -> None:
    if value:
        typer.echo(f"blockloc {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks and debug logs."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Info-level logs."),
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                 help="Print the version and exit."),
) -> None:
    _state["debug"] = debug
    level = logging.DEBUG if debug else (logging.INFO if verbose else logging.WARNING)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")


def _console():
    from rich.console import Console

    return Console()


def _load_cfg(config: Optional[str], preset: Optional[str] = None):
    from blockloc.config import load_config

    return load_config(config or preset)


# ----------------------------------------------------------------------------- eval


@app.command("eval")
def eval_cmd(
    gt: Path = typer.Option(..., "--gt", help="Ground truth: TUM, KITTI or NCLT groundtruth csv."),
    est: Path = typer.Option(..., "--est", help="Estimate: TUM or KITTI."),
    align: bool = typer.Option(False, "--align", help="Umeyama SE(3) alignment before ATE."),
    json_out: bool = typer.Option(False, "--json", help="Print one JSON object."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Directory for PNG plots."),
    max_time_diff: float = typer.Option(0.02, "--max-time-diff", help="Association tolerance, s."),
    interpolate: bool = typer.Option(False, "--interpolate",
                                     help="Interpolate ground truth to the estimate's stamps (else nearest)."),
    rpe_deltas: str = typer.Option("1,10,100", "--rpe-deltas", help="RPE path-length deltas, m, comma separated."),
) -> None:
    """ATE (translation and full xyzrpy), rotation RMSE and RPE of an estimate against ground truth."""
    from blockloc.evaluation.report import evaluate_files, parse_deltas, print_metrics

    metrics = evaluate_files(gt, est, align=align, max_time_diff_s=max_time_diff, plot_dir=plot,
                             interpolate=interpolate, rpe_deltas_m=parse_deltas(rpe_deltas))
    if json_out:
        import json

        typer.echo(json.dumps(metrics))
    else:
        print_metrics(metrics, _console())


# ----------------------------------------------------------------------------- sim
# @sim-commands (anchor: the sim stage adds its command above this line)

# ----------------------------------------------------------------------------- map
# @map-commands (anchor: the maps stage adds its commands above this line)

# ----------------------------------------------------------------------------- init
# @init-commands (anchor: the global-init stage adds its command above this line)

# ----------------------------------------------------------------------------- track / demo
# @track-commands (anchor: the tracking stage adds its commands above this line)


def main() -> None:
    """Console-script entry point: run the app, turn known errors into one line."""
    from blockloc.errors import BlocklocError

    try:
        app(standalone_mode=False)
    except BlocklocError as exc:
        if _state["debug"]:
            raise
        typer.echo(f"error: {exc}", err=True)
        sys.exit(2)
    except (typer.Exit, SystemExit) as exc:
        code = getattr(exc, "exit_code", getattr(exc, "code", 0))
        sys.exit(code or 0)
    except typer.Abort:
        typer.echo("aborted", err=True)
        sys.exit(130)
    except KeyboardInterrupt:
        typer.echo("interrupted", err=True)
        sys.exit(130)
    except Exception as exc:  # click usage errors and the unexpected
        import click

        if isinstance(exc, click.exceptions.ClickException):
            exc.show()
            sys.exit(exc.exit_code)
        if _state["debug"]:
            raise
        typer.echo(f"error: {type(exc).__name__}: {exc} (rerun with --debug for a traceback)", err=True)
        sys.exit(1)


if __name__ == "__main__":
    main()
