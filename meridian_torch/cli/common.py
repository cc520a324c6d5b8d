"""What the commands share: the --config and --set options with the config they give, the one error
boundary, progress bars, and the message of a command interrupted while writing a folder."""

from __future__ import annotations

import errno
import functools
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any, Callable

import typer

from meridian_torch.config import MeridianConfig, load_config
from meridian_torch.errors import MeridianError

__all__ = ["ConfigOption", "SetOption", "config_from_options", "error_boundary", "interruptible", "progress_bar"]

ConfigOption = Annotated[
    Path | None,
    typer.Option("--config", "-c", help="YAML config file (default: configs/default.yaml).", dir_okay=False),
]
SetOption = Annotated[
    list[str] | None,
    typer.Option("--set", "-s", help="Override a config key, e.g. --set sim.seed=3 (repeatable)."),
]


# Operating-system errors that are the user's situation, not a bug: permissions, a full or
# read-only disk, something in the way. They get one line like our own errors.
_USER_OS_ERRORS = {errno.EACCES, errno.EPERM, errno.EEXIST, errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EISDIR,
                   errno.ENOTDIR, errno.ENOENT, errno.ENOTEMPTY}


@contextmanager
def _terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM (a job scheduler, `kill`, a robot's shutdown) unwinds like Ctrl-C, so the same
    clean-up runs: temporary folders are removed and outputs left as they were."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _wraps_interrupt(exc: BaseException) -> bool:
    """An interrupt that a compiled extension turned into another error: the signal handler raised
    KeyboardInterrupt while, e.g., numba's dispatcher ran Python code, and CPython reports a
    SystemError ("returned a result with an exception set") caused by the interrupt. Ctrl-C itself
    counts too. An explicit exit is the command's own decision, whatever it was handling."""
    if isinstance(exc, (typer.Exit, SystemExit)):
        return False
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            return True
        seen.add(id(cause))
        cause = cause.__cause__ or (None if cause.__suppress_context__ else cause.__context__)
    return False


def error_boundary(command: Callable[..., Any]) -> Callable[..., Any]:
    """MeridianError and the user's OS errors (permission, disk full, file in the way) -> one line on
    stderr and exit code 1; Ctrl-C (also when an extension wrapped it) -> a line and exit code 130;
    anything else keeps its traceback."""

    @functools.wraps(command)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            with _terminate_as_interrupt():
                return command(*args, **kwargs)
        except BaseException as exc:
            if _wraps_interrupt(exc):
                typer.echo("interrupted", err=True)
                raise typer.Exit(130) from None
            if isinstance(exc, MeridianError):
                typer.echo(f"error: {exc}", err=True)
                raise typer.Exit(1) from None
            if isinstance(exc, OSError) and exc.errno in _USER_OS_ERRORS:
                where = f"{exc.filename}: " if exc.filename else ""
                typer.echo(f"error: {where}{exc.strerror or exc}", err=True)
                raise typer.Exit(1) from None
            raise

    return wrapper


def config_from_options(config: Path | None, overrides: list[str] | None) -> MeridianConfig:
    return load_config(config, overrides or [])


@contextmanager
def progress_bar(desc: str, unit: str) -> Iterator[Callable[[int, int], None]]:
    """A tqdm bar for the block; yields its `update(done, total)` callback and closes it on exit."""
    from tqdm import tqdm

    bar = tqdm(desc=desc, unit=unit, dynamic_ncols=True)

    def update(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    try:
        yield update
    finally:
        bar.close()


@contextmanager
def interruptible(out: Path) -> Iterator[None]:
    """Ctrl-C inside the block: say that `out` was left as it was (the block writes into a temporary
    folder that only replaces `out` when complete) and exit 130."""
    try:
        yield
    except BaseException as exc:
        if not _wraps_interrupt(exc):
            raise
        typer.echo(f"interrupted: nothing was written, {out} is as it was", err=True)
        raise typer.Exit(130) from None
