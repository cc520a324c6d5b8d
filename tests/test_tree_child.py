"""The benchmarks' side-by-side runs (scripts/_tree_child.py): a shipped config is read from the
other tree's own configs/, any other config path is kept."""

from __future__ import annotations

import sys

from conftest import REPO

sys.path.insert(0, str(REPO / "scripts"))

from _tree_child import config_in_tree  # noqa: E402


def test_shipped_config_is_read_from_the_other_tree(tmp_path):
    other = tmp_path / "old-tree"
    (other / "configs").mkdir(parents=True)
    (other / "configs" / "kitti09.yaml").write_text("extends: default.yaml\n")
    assert config_in_tree(REPO / "configs" / "kitti09.yaml", other) == other / "configs" / "kitti09.yaml"
    # a config the other tree lacks, a config outside configs/, no other tree, no config: unchanged
    assert config_in_tree(REPO / "configs" / "demo.yaml", other) == REPO / "configs" / "demo.yaml"
    outside = tmp_path / "mine.yaml"
    assert config_in_tree(outside, other) == outside
    assert config_in_tree(REPO / "configs" / "kitti09.yaml", None) == REPO / "configs" / "kitti09.yaml"
    assert config_in_tree(None, other) is None
