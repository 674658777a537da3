"""The operator console: a web page over one platform's view of its federation.

`OperatorConsole` runs beside a `FederationPlatform` (``dyknow console``, or any
application's operator). What it streams from every other member, and how its page
draws it, comes from the platform config's ``[console]`` section (`ConsoleSettings`,
`ConsoleRoles`): any federation's labels, none built in. Who may use it is
`ConsoleAccess` (a token, the allowed ``Host`` names, a same-site ``Origin``);
`configured_token` and `allowed_names` read the operator's choices; `serve` listens
with what one client may cost bounded. docs/console.md.
"""

from .._platform import ConsoleRoles, ConsoleSettings
from ._access import (
    ALLOW_HOSTS_ENV,
    IDLE_TIMEOUT,
    MAX_CLIENTS,
    MAX_CLIENTS_PER_ADDRESS,
    TOKEN_ENV,
    ConsoleAccess,
    allowed_names,
    check_token,
    configured_token,
    new_token,
    serve,
)
from ._server import OperatorConsole

__all__ = [
    "ALLOW_HOSTS_ENV",
    "IDLE_TIMEOUT",
    "MAX_CLIENTS",
    "MAX_CLIENTS_PER_ADDRESS",
    "TOKEN_ENV",
    "ConsoleAccess",
    "ConsoleRoles",
    "ConsoleSettings",
    "OperatorConsole",
    "allowed_names",
    "check_token",
    "configured_token",
    "new_token",
    "serve",
]
