"""For benchmarks that compare package trees side by side: run a script again in a fresh
interpreter that imports the package from a given source tree (PYTHONPATH), and read back the
JSON result it prints on a line starting with its tag."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path


def config_in_tree(config: Path | None, source: Path | str | None) -> Path | None:
    """The config a run on `source` reads: a file of this checkout's configs/ becomes the same file
    of `source` (each tree at its own shipped defaults; an older tree refuses keys added since),
    any other path stays."""
    if config is None or source is None:
        return config
    try:
        relative = Path(config).resolve().relative_to(Path(__file__).resolve().parents[1] / "configs")
    except ValueError:
        return config
    theirs = Path(source) / "configs" / relative
    return theirs if theirs.exists() else config


def run_in_tree(script: str, argv: list[str], source: Path | str | None, tag: str,
                env: dict[str, str] | None = None) -> dict:
    """`python script *argv` with `source` first on PYTHONPATH (None: this environment's package);
    its stderr streams through, its last `tag` line of stdout is returned parsed."""
    child_env = dict(os.environ if env is None else env)
    if source is not None:
        child_env["PYTHONPATH"] = os.pathsep.join([str(source)] + [p for p in [child_env.get("PYTHONPATH")] if p])
    name = Path(script).stem
    proc = subprocess.run([sys.executable, str(Path(script).resolve()), *argv], env=child_env,
                          stdout=subprocess.PIPE, text=True)
    lines = [x for x in proc.stdout.splitlines() if x.startswith(tag)]
    if proc.returncode != 0 or not lines:
        sys.stderr.write(proc.stdout)
        what = f"exit {proc.returncode}" if proc.returncode != 0 else "no result line"
        raise SystemExit(f"{name}: the run on {source or 'this environment'} failed ({what})")
    return json.loads(lines[-1][len(tag):])
