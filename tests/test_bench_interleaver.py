"""The time-to-accuracy benchmark's interleaving: runs take turns, each clock counts its own."""
from __future__ import annotations

import time

from bench.training import Interleaver


def _job(name: str, steps: int, step_s: float, order: list[str]):  # noqa: ANN202
    def run(progress) -> str:  # noqa: ANN001
        for i in range(1, steps + 1):
            time.sleep(step_s)
            order.append(name)
            if i % 2 == 0:  # an evaluation every 2 steps ends the turn
                progress.advance(2, loss=0.0, val=float(-i))
        return name
    return run


def test_runs_alternate_by_finished_share_and_clocks_count_only_their_own_turns():
    order: list[str] = []
    interleaver = Interleaver({"long": 8, "short": 4})
    results = interleaver.run({"long": _job("long", 8, 0.01, order),
                               "short": _job("short", 4, 0.03, order)})
    assert results == {"long": "long", "short": "short"}
    # Turns of one evaluation interval; the run with the smaller finished share goes next.
    assert "".join(x[0] for x in order) == "llssllllssll"
    # Own clocks: 8 x 10 ms and 4 x 30 ms, not the 200 ms both runs took together.
    assert 0.075 <= interleaver.seconds["long"] < 0.17
    assert 0.115 <= interleaver.seconds["short"] < 0.2
    assert [e[0] for e in interleaver.evaluations["short"]] == [2, 4]
    assert [e[2] for e in interleaver.evaluations["long"]] == [-2.0, -4.0, -6.0, -8.0]
    seconds = [e[1] for e in interleaver.evaluations["long"]]
    assert seconds == sorted(seconds) and seconds[-1] <= interleaver.seconds["long"]
