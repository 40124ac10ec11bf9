"""CiA 301 heartbeat consumer: which nodes went silent, judged against a time the caller passes in.

python canopen's master records heartbeats but never times them out (its issue 543); this
consumer does. A node is *lost* when its last heartbeat (or, before the first one, the start of
consumption) is older than the consumer time; it is *back* when a heartbeat arrives again. Each
loss is reported once, by :meth:`HeartbeatConsumer.newly_lost`.
"""

from __future__ import annotations

import math

from hal.canopen.cia301.nmt import NmtState

__all__ = ["HeartbeatConsumer"]

#: How much earlier than the exact due time :meth:`HeartbeatConsumer.newly_lost` looks again, s: its
#: skip never hides a loss that the exact test ``now - last > timeout`` would find (rounding of the sum).
_DUE_MARGIN_S = 1e-9


class HeartbeatConsumer:
    """Heartbeat watchdog of several nodes.

    Args:
        node_ids: the nodes watched.
        timeout_s: the consumer time, s: a node silent longer is lost.
    """

    def __init__(self, node_ids: tuple[int, ...], timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self._last_s: dict[int, float] = dict.fromkeys(node_ids, 0.0)
        self._state: dict[int, NmtState | None] = dict.fromkeys(node_ids, None)
        self._lost: set[int] = set()
        self._quiet_until_s = -math.inf  # no node can be newly lost before this time (-inf: look)

    def start(self, now_s: float) -> None:
        """Consume from ``now_s`` on: every node has one consumer time for its first heartbeat."""
        for node_id in self._last_s:
            self._last_s[node_id] = now_s
            self._state[node_id] = None
        self._lost.clear()
        self._quiet_until_s = -math.inf

    def on_heartbeat(self, node_id: int, state: NmtState, now_s: float) -> None:
        """A heartbeat (or boot-up message) of ``node_id`` in ``state`` arrived at ``now_s``."""
        if node_id in self._last_s:
            self._last_s[node_id] = now_s
            self._state[node_id] = state
            self._lost.discard(node_id)
            self._quiet_until_s = -math.inf

    def state(self, node_id: int) -> NmtState | None:
        """The NMT state the node's last heartbeat reported (None before the first)."""
        return self._state[node_id]

    def silent_s(self, node_id: int, now_s: float) -> float:
        """How long ``node_id`` has been silent at ``now_s``, s."""
        return now_s - self._last_s[node_id]

    def is_lost(self, node_id: int) -> bool:
        return node_id in self._lost

    def newly_lost(self, now_s: float) -> list[int]:
        """Nodes whose heartbeat is overdue at ``now_s`` and were not lost before (each loss reported once)."""
        found: list[int] = []
        if now_s < self._quiet_until_s:  # nearly every tick: no heartbeat can be overdue yet (issue 25)
            return found
        watched = [last_s for node_id, last_s in self._last_s.items() if node_id not in self._lost]
        for node_id, last_s in self._last_s.items():
            if node_id not in self._lost and now_s - last_s > self.timeout_s:
                self._lost.add(node_id)
                found.append(node_id)
        if not found and watched:
            self._quiet_until_s = min(watched) + self.timeout_s - _DUE_MARGIN_S
        return found
