"""The frames' queues between Zenoh's thread and the loop (protocols._handoff.FairQueues): one per
unit, taken in turn; the drop policy of deploy/SCALING.md "Queues and drops"."""

from __future__ import annotations

import asyncio

from protocols._handoff import FairQueues


def drain(queues: FairQueues[str, str]) -> list[str]:
    out = []
    while (item := queues.get_nowait()) is not None:
        out.append(item)
    return out


def test_a_full_queue_drops_its_unit_s_new_items_and_costs_no_other_unit():
    loop = asyncio.new_event_loop()
    try:
        queues: FairQueues[str, str] = FairQueues(capacity=3, total=100, loop=loop)
        for k in range(10):
            queues.put("flood", f"f{k}")
        queues.put("steady", "s0")
        assert queues.dropped == {"flood": 7} and queues.received == {"flood": 10, "steady": 1}
        # Taken in turn, each unit's oldest first: the steady unit waits behind one frame, not three.
        assert drain(queues) == ["f0", "s0", "f1", "f2"]
    finally:
        loop.close()


def test_past_the_instance_s_total_a_unit_under_its_fair_share_takes_the_longest_queue_s_newest():
    """capacity 4, total 6: A holds 4 and B 2, the total is full. C (nothing queued, share 6 / 3 = 2)
    takes the place of A's newest; B, at its share, has its new item dropped."""
    loop = asyncio.new_event_loop()
    try:
        queues: FairQueues[str, str] = FairQueues(capacity=4, total=6, loop=loop)
        for k in range(4):
            queues.put("A", f"a{k}")
        for k in range(2):
            queues.put("B", f"b{k}")
        queues.put("C", "c0")
        queues.put("B", "b2")
        assert len(queues) == 6
        assert queues.dropped == {"A": 1, "B": 1}
        assert drain(queues) == ["a0", "b0", "c0", "a1", "b1", "a2"]
    finally:
        loop.close()
