"""Stage timings: nested names, call counts, nothing recorded outside a recording, per thread."""

from __future__ import annotations

import threading

from meridian_torch.core.timing import record_stages, stage


def test_nested_stages_are_recorded_under_their_parents():
    with record_stages() as times:
        for _ in range(3):
            with stage("matching"):
                with stage("affinity"):
                    pass
                with stage("particles"):
                    pass
        with stage("consistency"):
            pass
    assert list(times.seconds) == ["matching/affinity", "matching/particles", "matching", "consistency"]
    assert times.calls == {"matching/affinity": 3, "matching/particles": 3, "matching": 3, "consistency": 1}
    assert times.seconds["matching"] >= times.seconds["matching/affinity"] + times.seconds["matching/particles"]
    assert times.total("affinity") == times.seconds["matching/affinity"]


def test_a_stage_that_raises_is_still_recorded_and_unwound():
    with record_stages() as times:
        try:
            with stage("outer"):
                with stage("inner"):
                    raise RuntimeError("boom")
        except RuntimeError:
            pass
        with stage("after"):
            pass
    assert set(times.calls) == {"outer/inner", "outer", "after"}


def test_nothing_is_recorded_outside_a_recording_or_in_other_threads():
    with stage("before"):  # no recording: a no-op
        pass

    def worker() -> None:
        with stage("in a thread"):
            pass

    with record_stages() as times:
        t = threading.Thread(target=worker)
        t.start()
        t.join()
        with stage("main"):
            pass
    with stage("after"):
        pass
    assert list(times.calls) == ["main"]


def test_threads_in_a_copied_context_record_their_own_paths_into_one_table():
    """What the ground mapper's perception thread does: stages opened there nest under the stage that
    was open when its work was submitted, and never under what the main thread opened meanwhile."""
    import contextvars

    started, release = threading.Event(), threading.Event()

    def worker() -> None:
        with stage("perceive"):
            started.set()
            release.wait(5)
            with stage("segmentation"):
                pass

    with record_stages() as times:
        with stage("ground mapping"):
            context = contextvars.copy_context()
        t = threading.Thread(target=context.run, args=(worker,))
        t.start()
        started.wait(5)
        with stage("tracking"):  # open in the main thread while the worker is inside "perceive"
            release.set()
            t.join()
    assert set(times.calls) == {"ground mapping", "ground mapping/perceive", "ground mapping/perceive/segmentation",
                                "tracking"}


def test_a_new_recording_starts_its_paths_afresh():
    with record_stages() as outer:
        with stage("outer"):
            with record_stages() as inner:
                with stage("inner"):
                    pass
    assert list(inner.calls) == ["inner"] and list(outer.calls) == ["outer"]
