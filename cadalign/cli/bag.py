"""``cadalign bag topics BAG``: the image topics of a ROS 1 bag or ROS 2 bag folder (to pick ``--topic``)."""

from __future__ import annotations

from pathlib import Path

import typer

from cadalign.cli.common import console, user_errors

app = typer.Typer(help="Inspect ROS bags (the input of sfm, build-dataset and infer with --topic).",
                  no_args_is_help=True)


@app.command("topics")
def topics(bag: Path = typer.Argument(..., help="A ROS 1 .bag file or a ROS 2 bag folder (metadata.yaml).")) -> None:
    """List the bag's image topics (sensor_msgs/Image, CompressedImage) with their message counts."""
    from cadalign.formats.bag import image_topics  # lazy: pulls cv2; keeps `cadalign --help` light

    with user_errors():
        found = image_topics(bag)
    if not found:
        console.print(f"[yellow]{bag} has no image topic[/]")
        raise typer.Exit(code=1)
    for t in found:
        typer.echo(f"{t.name}\t{t.msgtype}\t{t.count}")
