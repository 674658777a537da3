"""DyKnow Federation: the federation service, export and import proxies, fusion, platform assembly.

`FederationPlatform` (configured by a `PlatformConfig`, usually a TOML file) is one
member of a federation; `FederationAgent` is its DyKnow Federation service, the proxies
carry agreed streams, and `add_fusion` merges an imported stream with a local one.
`GatewayAgent` is the ACL face of the local DyKnow instance (its content mapping is
`GatewayService`); it lives here, not in `agents`, which knows nothing of DyKnow.
`FoxgloveBridge` serves a platform's view of its federation to Foxglove (docs/foxglove.md);
it is imported on first use, which a node (``dyknow node``) never makes.
"""

from typing import TYPE_CHECKING, Any

from ._export import Export, ExportProxy
from ._fusion import Fusion, add_fusion
from ._gateway import GATEWAY_SERVICE_TYPE, GatewayAgent, GatewayStats
from ._gateway_service import GatewayRefusal, GatewayService
from ._import import Import, ImportProxy
from ._platform import (
    DEFAULT_IMPORT_LABEL,
    DfEventLimitSettings,
    FactSettings,
    FederationPlatform,
    FoxgloveSettings,
    KxLimitSettings,
    MqttSettings,
    PlatformConfig,
    PlatformConfigError,
    RateLimitSettings,
    ZenohSettings,
    load_sharing,
)
from ._service import (
    FEDERATION_AGENT,
    FEDERATION_SERVICE_TYPE,
    ONTOLOGY,
    Anchor,
    Consent,
    Exporter,
    FederationAgent,
    GlobalResult,
    ImportAgreements,
    LabelSearch,
    LabelTranslator,
    MembershipEvent,
    StreamExport,
)
from ._sessions import InterfaceSessions, SessionsProvider, TableSessions
from ._sharing import Sharing, SharingRule, SharingSettings

if TYPE_CHECKING:
    from ._foxglove import FoxgloveBridge

__all__ = [
    "DEFAULT_IMPORT_LABEL",
    "FEDERATION_AGENT",
    "FEDERATION_SERVICE_TYPE",
    "GATEWAY_SERVICE_TYPE",
    "ONTOLOGY",
    "Anchor",
    "Consent",
    "DfEventLimitSettings",
    "Export",
    "ExportProxy",
    "Exporter",
    "FactSettings",
    "FederationAgent",
    "FederationPlatform",
    "FoxgloveBridge",
    "FoxgloveSettings",
    "Fusion",
    "GatewayAgent",
    "GatewayRefusal",
    "GatewayService",
    "GatewayStats",
    "GlobalResult",
    "Import",
    "ImportAgreements",
    "ImportProxy",
    "InterfaceSessions",
    "KxLimitSettings",
    "LabelSearch",
    "LabelTranslator",
    "MembershipEvent",
    "MqttSettings",
    "PlatformConfig",
    "PlatformConfigError",
    "RateLimitSettings",
    "SessionsProvider",
    "Sharing",
    "SharingRule",
    "SharingSettings",
    "StreamExport",
    "TableSessions",
    "ZenohSettings",
    "add_fusion",
    "load_sharing",
]


def __getattr__(name: str) -> Any:
    """``FoxgloveBridge``, imported from ``_foxglove`` on first use (then a plain attribute)."""
    if name == "FoxgloveBridge":
        from ._foxglove import FoxgloveBridge

        globals()[name] = FoxgloveBridge
        return FoxgloveBridge
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
