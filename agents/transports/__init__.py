"""Transports: one interface (pub/sub, query/serve, liveliness), several implementations.

``MemoryTransport`` (one process, the tests' double), ``ZenohTransport`` (the default) and
``MqttTransport`` (through an MQTT v5 broker) behave the same; see each module's docstring
for what differs.

A platform imports the transport it speaks: the MQTT and in-memory transports are imported
at their first use (``agents.transports.MqttTransport``), not with this package; MQTT's
settings are, as every platform's config may name them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ._base import (
    Handle,
    Inbox,
    Message,
    Presence,
    QueryFilter,
    QueryHandler,
    Replies,
    Reply,
    Subscription,
    Transport,
    free_tcp_port,
    key_intersects,
    key_matches,
)
from ._mqtt_config import MqttConfig, MqttTls
from ._zenoh import ZenohConfig, ZenohTls, ZenohTransport, ZenohUser

if TYPE_CHECKING:
    from ._memory import MemoryHub, MemoryTransport
    from ._mqtt import MqttTransport, mqtt_client

# what is imported at its first use: name -> its module
_LAZY = {
    "MemoryHub": "_memory",
    "MemoryTransport": "_memory",
    "MqttTransport": "_mqtt",
    "mqtt_client": "_mqtt",
}

__all__ = [
    "Handle",
    "Inbox",
    "MemoryHub",
    "MemoryTransport",
    "Message",
    "MqttConfig",
    "MqttTls",
    "MqttTransport",
    "Presence",
    "QueryFilter",
    "QueryHandler",
    "Replies",
    "Reply",
    "Subscription",
    "Transport",
    "ZenohConfig",
    "ZenohTls",
    "ZenohTransport",
    "ZenohUser",
    "free_tcp_port",
    "key_intersects",
    "key_matches",
    "mqtt_client",
]


def __getattr__(name: str) -> Any:
    """A transport not imported with the package (`_LAZY`), imported now."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib import import_module

    value = getattr(import_module(f".{module}", __name__), name)
    globals()[name] = value  # the next lookup finds it without this function
    return value
