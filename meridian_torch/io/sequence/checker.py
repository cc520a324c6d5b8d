"""check_sequence: every problem of a sequence folder at once, images and orthophoto included."""

from __future__ import annotations

from pathlib import Path

from meridian_torch.io.ortho import check_orthophoto
from meridian_torch.io.poses import PathLike, parse_tum
from meridian_torch.io.sequence.camera_json import parse_camera
from meridian_torch.io.sequence.images import check_depth, check_rgb, decode_image, open_image
from meridian_torch.io.sequence.text_files import (
    check_covers,
    odometry_gap_problems,
    parse_frames,
    parse_meta,
)

__all__ = ["check_sequence"]


def check_sequence(path: PathLike, max_odometry_gap_s: float | None = None, *, quick: bool = False) -> list[str]:
    """Every problem of a sequence folder, each naming its file; an empty list means valid.

    `max_odometry_gap_s` (default: the config default) also reports frames inside longer gaps
    between odometry poses. Every image is decoded (a truncated file is found here, not at its
    frame in the middle of a run); `quick` reads the headers only.

    Unlike SequenceReader this also checks every listed image (existence, format, bit depth,
    size vs camera.json, from the headers only) and the orthophoto.
    """
    root = Path(path)
    if not root.is_dir():
        return [f"{root}: not a folder"]
    ground = root / "ground"
    problems: list[str] = []
    if not ground.is_dir():
        problems.append(f"{ground}: folder missing")
    camera = parse_camera(ground / "camera.json", problems)
    table = parse_frames(ground / "frames.csv", problems)
    if table is not None:
        for line, rgb_path, depth_path in zip(table.lines, table.rgb, table.depth):
            for img_path, check in ((rgb_path, check_rgb), (depth_path, check_depth)):
                img = open_image(img_path, line, problems)
                if img is not None:
                    with img:
                        check(img, img_path, camera, problems)
                        if not quick:
                            decode_image(img, img_path, problems)
    odometry, odom_problems = parse_tum(ground / "odometry.tum")
    problems += odom_problems
    if odometry is not None and table is not None and len(table.times):
        check_covers(odometry, table.times, ground / "odometry.tum", problems)
        if max_odometry_gap_s is None:
            from meridian_torch.config import GroundMapConfig

            max_odometry_gap_s = GroundMapConfig().max_odometry_gap_s
        problems += odometry_gap_problems(odometry, table.times, ground / "odometry.tum", max_odometry_gap_s)
    if (root / "groundtruth.tum").exists():
        problems += parse_tum(root / "groundtruth.tum")[1]
    if (root / "meta.json").exists():
        parse_meta(root / "meta.json", problems)
    problems += check_orthophoto(root / "aerial")
    return problems
