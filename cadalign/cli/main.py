"""Entry point: ``cadalign [--log-level L] [--version] COMMAND ...``."""

from __future__ import annotations

import typer

from cadalign import __version__
from cadalign.cli import align, bag, bench, build_dataset, common, demo, emulate, sfm, sim
from cadalign.cli import eval as eval_cli
from cadalign.cli import fuse as fuse_cli
from cadalign.cli import infer as infer_cli
from cadalign.cli import train as train_cli

app = typer.Typer(
    name="cadalign",
    help="CAD-aligned ground truth, models, maps and emulated sensors for underwater inspection robots.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"cadalign {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    log_level: str = typer.Option("info", "--log-level", help=f"One of {', '.join(common.LOG_LEVELS)}."),
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version."),
) -> None:
    if log_level.lower() not in common.LOG_LEVELS:
        raise typer.BadParameter(f"{log_level!r}; allowed: {', '.join(common.LOG_LEVELS)}", param_hint="--log-level")
    common.setup_logging(log_level)


app.command("sim")(sim.command)
app.command("sfm")(sfm.command)
app.command("align")(align.command)
app.command("build-dataset")(build_dataset.command)
app.command("demo")(demo.command)
app.add_typer(bench.app, name="bench")
app.add_typer(bag.app, name="bag")
app.add_typer(train_cli.app, name="train")
app.add_typer(eval_cli.app, name="eval")
app.add_typer(emulate.app, name="emulate")
app.command("infer")(infer_cli.command)
app.command("fuse")(fuse_cli.command)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
