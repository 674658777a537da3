"""Transports: one interface (pub/sub, query/serve, liveliness), several implementations.

``MemoryTransport`` (one process, the tests' double), ``ZenohTransport`` (the default) and
``MqttTransport`` (through an MQTT v5 broker) behave the same; see each module's docstring
for what differs.
"""

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
from ._memory import MemoryHub, MemoryTransport
from ._mqtt import MqttConfig, MqttTls, MqttTransport
from ._zenoh import ZenohConfig, ZenohTls, ZenohTransport, ZenohUser

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
]
