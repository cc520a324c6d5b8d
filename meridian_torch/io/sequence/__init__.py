"""Sequence folders (README, Formats): strict reader, whole-folder checker and atomic writer.

One module per part: `camera_json` (ground/camera.json), `text_files` (frames.csv, odometry
coverage, meta.json), `images` (frame images), `reader`, `checker` and `writer`; `problems`
holds how collected problems are raised.
"""

from meridian_torch.io.sequence.camera_json import read_camera
from meridian_torch.io.sequence.checker import check_sequence
from meridian_torch.io.sequence.reader import Frame, SequenceReader
from meridian_torch.io.sequence.writer import SequenceWriter

__all__ = ["Frame", "read_camera", "SequenceReader", "SequenceWriter", "check_sequence"]
