"""DyKnow Federation: the federation service, export and import proxies, fusion, platform assembly.

`FederationPlatform` (configured by a `PlatformConfig`, usually a TOML file) is one
member of a federation; `FederationAgent` is its DyKnow Federation service, the proxies
carry agreed streams, and `add_fusion` merges an imported stream with a local one.
"""

from ._fusion import Fusion, add_fusion
from ._platform import (
    DEFAULT_IMPORT_LABEL,
    FederationPlatform,
    KxLimitSettings,
    MqttSettings,
    PlatformConfig,
    PlatformConfigError,
    RateLimitSettings,
    ZenohSettings,
)
from ._proxies import (
    Export,
    ExportProxy,
    Import,
    ImportProxy,
    InterfaceSessions,
    SessionsProvider,
    TableSessions,
)
from ._service import (
    FEDERATION_AGENT,
    FEDERATION_SERVICE_TYPE,
    ONTOLOGY,
    Anchor,
    Exporter,
    FederationAgent,
    GlobalResult,
    LabelSearch,
    LabelTranslator,
    MembershipEvent,
    StreamExport,
)

__all__ = [
    "DEFAULT_IMPORT_LABEL",
    "FEDERATION_AGENT",
    "FEDERATION_SERVICE_TYPE",
    "ONTOLOGY",
    "Anchor",
    "Export",
    "ExportProxy",
    "Exporter",
    "FederationAgent",
    "FederationPlatform",
    "Fusion",
    "GlobalResult",
    "Import",
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
    "StreamExport",
    "TableSessions",
    "ZenohSettings",
    "add_fusion",
]
