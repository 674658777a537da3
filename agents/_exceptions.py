"""Errors raised by the agent layer.

The tree (all exported from `agents`); the `ConversationError` branch is defined beside
`Conversation` in ``_agent``, as it carries an ACL message, so that this module imports
nothing::

    AgentError
    ├── MessageError            (a message that does not parse or validate; .reason says why)
    ├── ConversationError       (a protocol step went wrong)
    │   ├── ReplyTimeout        (also a TimeoutError: no reply by reply_by / the deadline)
    │   ├── Refused             (the responder refused; .message is the refuse)
    │   ├── Failed              (the responder agreed, then failed; .message is the failure)
    │   └── NotUnderstood       (the responder did not understand; .message)
    ├── ServiceError            (Directory Facilitator: unknown service, visibility …)
    ├── SecurityError           (authentication or access control refused something)
    │   ├── KeyFileError        (a key file or the trust file is missing, malformed or too open)
    │   └── AuthenticationError (a handshake or envelope was refused; .code .reason .platform)
    │       ├── Malformed       (not a handshake message / sealed envelope we can read)
    │       │   └── Unencrypted (a plain envelope where encryption is required)
    │       ├── Misdirected     (wrong federation, or addressed to another platform)
    │       ├── UnknownPlatform (the sender is not in the trust file)
    │       ├── UnknownSession  (no such session, or no handshake of ours pending)
    │       ├── Forged          (bad MAC or signature: forged or tampered)
    │       ├── Replayed        (counter or handshake nonce already seen, or too old)
    │       └── Expired         (timestamp outside the allowed skew, or the session is over)
    └── TransportError          (the transport failed; zenoh/MQTT errors are converted here)
        └── TransportClosed     (used after close, or the connection went away)
"""

from __future__ import annotations


class AgentError(Exception):
    """Base class of every error raised by `agents`."""


class MessageError(AgentError, ValueError):
    """A message that does not parse or validate; ``reason`` is what a not-understood says."""

    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(reason)


class ServiceError(AgentError):
    """A Directory Facilitator operation is not allowed or names an unknown service."""


class SecurityError(AgentError):
    """Authentication, replay protection or access control refused a message."""


class KeyFileError(SecurityError):
    """A key or trust file is missing, malformed or too open; the message names file and key."""

    def __init__(self, path: object, problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


class AuthenticationError(SecurityError):
    """A handshake message or sealed envelope was refused.

    ``code`` is a short stable word for audit records, ``reason`` the human explanation and
    ``platform`` the sender the message claims (``None`` when it could not be read). Nothing
    in a refused message is trustworthy, so a receiver drops it rather than answering.
    """

    code = "refused"

    def __init__(self, reason: str, platform: str | None = None) -> None:
        self.reason = reason
        self.platform = platform
        super().__init__(reason)


class Malformed(AuthenticationError):
    """Not a handshake message or sealed envelope of a version this side speaks."""

    code = "malformed"


class Unencrypted(Malformed):
    """A plain (MAC-only) envelope sent to a platform that requires encryption."""

    code = "unencrypted"


class Misdirected(AuthenticationError):
    """Meant for another federation or another platform."""

    code = "misdirected"


class UnknownPlatform(AuthenticationError):
    """The claimed sender is not in the trust file (never was, or was removed)."""

    code = "untrusted"


class UnknownSession(AuthenticationError):
    """No session with this id (never made, renewed away, or forgotten), or no handshake pending."""

    code = "unknown-session"


class Forged(AuthenticationError):
    """The MAC or signature does not verify: forged, or tampered with on the way."""

    code = "forged"


class Replayed(AuthenticationError):
    """Seen before (counter or handshake nonce), or older than the replay window."""

    code = "replayed"


class Expired(AuthenticationError):
    """The timestamp is outside the allowed clock skew, or the session is past its lifetime."""

    code = "expired"


class TransportError(AgentError):
    """The transport (zenoh, MQTT, memory) failed."""


class TransportClosed(TransportError):
    """The transport is closed, or its connection went away."""
