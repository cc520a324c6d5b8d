"""The `meridian-torch` command: a thin layer over the package with one error boundary.

Commands live by group: `sequences` (check, simulate, convert), `maps` (build-map, show-map,
map-ground), `runs` (localize, evaluate, demo) and `models` (fit-vocabulary, export, models);
`common` holds what they share. They are registered here, in the order `--help` lists them.
Heavy modules (simulator, renderer, matplotlib) are imported inside the commands that use them.
"""

from __future__ import annotations

import os

# Idle OpenMP threads sleep instead of spinning: on a shared 2-core machine spinning threads made
# small torch ops 25-50x slower (measured); set before torch is first imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
from typing import Annotated

import typer

from meridian_torch import __version__
from meridian_torch.cli.common import ConfigOption, SetOption, config_from_options, error_boundary
from meridian_torch.cli.maps import build_map, map_ground_command, show_map
from meridian_torch.cli.models import export_onnx, fit_vocabulary, models_list, models_verify
from meridian_torch.cli.runs import demo, evaluate, localize
from meridian_torch.cli.sequences import (
    check,
    convert_kitti_command,
    convert_rosbag_command,
    convert_tum_rgbd_command,
    simulate,
)
from meridian_torch.config import dump_config

__all__ = ["app", "main"]

app = typer.Typer(
    name="meridian-torch",
    help="Cross-view geo-localization of a ground robot (RGB-D + odometry) in an aerial orthophoto.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
config_app = typer.Typer(help="Inspect configuration files.", no_args_is_help=True)
app.add_typer(config_app, name="config")
models_app = typer.Typer(help="List and verify local model files (models/manifest.yaml).", no_args_is_help=True)
app.add_typer(models_app, name="models")
convert_app = typer.Typer(help="Convert other recordings to a sequence folder (README, Formats).", no_args_is_help=True)
app.add_typer(convert_app, name="convert")


@app.callback(invoke_without_command=True)
def _root(
    version: Annotated[bool, typer.Option("--version", help="Print the version and exit.")] = False,
) -> None:
    if version:
        typer.echo(f"meridian-torch {__version__}")
        raise typer.Exit()


@config_app.command("show")
@error_boundary
def config_show(config: ConfigOption = None, set_: SetOption = None) -> None:
    """Print the fully resolved config (defaults, file and --set overrides) as YAML."""
    typer.echo(dump_config(config_from_options(config, set_)), nl=False)


app.command()(check)
app.command()(simulate)
convert_app.command("kitti")(convert_kitti_command)
convert_app.command("rosbag")(convert_rosbag_command)
convert_app.command("tum-rgbd")(convert_tum_rgbd_command)
app.command("build-map")(build_map)
app.command("show-map")(show_map)
app.command("map-ground")(map_ground_command)
app.command()(localize)
app.command()(evaluate)
app.command()(demo)
app.command("fit-vocabulary")(fit_vocabulary)
app.command("export")(export_onnx)
models_app.command("list")(models_list)
models_app.command("verify")(models_verify)


def main() -> None:
    """Console-script entry point."""
    app()
