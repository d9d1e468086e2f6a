"""The deliveries' wake-up (service.daemon): events stored wake every sink's delivery, and the intake
waits only for the deliveries that were idle, until each has handed the events to its transport."""

from __future__ import annotations

import asyncio

from service.daemon import _Wake


def test_stored_events_are_awaited_until_every_idle_delivery_has_sent_them():
    async def scenario() -> None:
        wake = _Wake(["zenoh", "mavlink"])
        assert wake.handed.is_set()  # nothing stored yet: nothing to wait for
        wake.idle("zenoh")
        wake.idle("mavlink")
        wake.set()
        assert all(e.is_set() for e in wake.events.values())
        assert not wake.handed.is_set()
        wake.sent("zenoh")
        assert not wake.handed.is_set()
        wake.sent("mavlink")
        assert wake.handed.is_set()

    asyncio.run(scenario())


def test_a_busy_delivery_is_not_waited_for():
    """A delivery waiting for an earlier event's acknowledgement (up to its timeout) takes the new events
    after it: the intake does not wait for it."""

    async def scenario() -> None:
        wake = _Wake(["zenoh", "mavlink"])
        wake.idle("mavlink")
        wake.set()
        assert not wake.handed.is_set()
        wake.sent("mavlink")
        assert wake.handed.is_set()
        # The idle delivery was woken: until it says idle again, a second store does not wait for it.
        wake.set()
        assert wake.handed.is_set()

    asyncio.run(scenario())


def test_a_delivery_not_heard_from_in_time_is_not_waited_for_again_until_idle():
    """A transport that blocks (a congested link) costs the intake one wait, not one per event."""

    async def scenario() -> None:
        wake = _Wake(["zenoh"])
        wake.idle("zenoh")
        wake.set()
        assert not wake.handed.is_set()
        wake.give_up()
        assert wake.handed.is_set()
        wake.set()  # more events while the delivery is still stuck in its transport
        assert wake.handed.is_set()
        wake.idle("zenoh")  # through at last: the next events are waited for again
        wake.set()
        assert not wake.handed.is_set()

    asyncio.run(scenario())
