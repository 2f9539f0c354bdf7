"""What the daemon and its OPC UA server process say over their channel (:class:`~autotuner.service.channel.Channel`).

The kinds (docs/opcua.md, "Off the sampling path"):

daemon → server
    ``("init", Init)`` first; ``("status", [status, …])`` the changed loops'
    compact statuses (:data:`SNAPSHOT_KEYS`) at the monitor's rate;
    ``("reply", call_id, reply)`` a method call's outcome; ``("stop",)``.
server → daemon
    ``("ready",)`` or ``("failed", message)`` once, after the init;
    ``("call", call_id, loop_id, action, body, user)`` a method (action tune,
    abort or apply; body the validated TUNE body for tune, else None);
    ``("log", logger, level, message)`` a log record for the daemon's log;
    ``("sessions", n)`` how many client sessions are open (when it changes).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from autotuner.service.channel import Channel
from autotuner.service.config import OpcUaConfig, OpcUaUser

__all__ = ["Channel", "Init", "SNAPSHOT_KEYS", "snapshot"]
# The members of a loop's REST status (Loop.as_json) the address space reads after the first one (which is whole:
# description and units too); the rest never change while the daemon runs or are not published.
SNAPSHOT_KEYS = ("id", "pv", "sp", "mv", "mode", "current_gains", "tbsy", "te", "ite", "stage", "progress", "message",
                 "session", "controller", "point", "static_gain", "gains", "pending_gains", "monitor_error", "health")


@dataclass(frozen=True)
class Init:
    """What the server process needs to start: its settings, users, endpoint and certificate folder, the log
    levels of the daemon (``levels``: logger name → level; "" the root), and every loop's whole status with its
    monitor period (wall seconds), in the config's order."""

    config: OpcUaConfig
    users: list[OpcUaUser]
    url: str
    cert_dir: Path
    levels: dict[str, int]
    loops: list[tuple[dict[str, Any], float]]


def snapshot(status: dict[str, Any]) -> dict[str, Any]:
    """The compact status of a loop sent at the monitor's rate: :data:`SNAPSHOT_KEYS` of its REST status."""
    return {key: status[key] for key in SNAPSHOT_KEYS}
