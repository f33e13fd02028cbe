"""Stage timings: exclusive of nested stages, adding up to the recorded block."""

import time

from latentsindy._core.timing import recording, stage, timed


def test_stages_are_exclusive_and_add_up_to_the_block():
    start = time.perf_counter()
    with recording() as seconds:
        with stage("outer"):
            time.sleep(0.02)
            with stage("inner"):
                time.sleep(0.03)
            with stage("inner"):
                time.sleep(0.01)
        time.sleep(0.01)
    total = time.perf_counter() - start
    assert set(seconds) == {"outer", "inner", "other"}
    assert 0.04 <= seconds["inner"] < 0.04 + 0.015
    assert 0.02 <= seconds["outer"] < 0.02 + 0.015  # the inner stages are not counted twice
    assert 0.01 <= seconds["other"] < 0.01 + 0.015
    assert abs(sum(seconds.values()) - total) < 1e-3


def test_outside_a_recording_stages_only_run_the_code():
    @timed("square")
    def square(v):
        return v * v

    with stage("nothing records this"):
        assert square(3) == 9
    with recording() as seconds:
        assert square(4) == 16
    assert set(seconds) == {"square", "other"}
