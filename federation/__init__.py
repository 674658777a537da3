"""DyKnow Federation: the federation service, export and import proxies, fusion, platform assembly.

`FederationPlatform` (configured by a `PlatformConfig`, usually a TOML file) is one
member of a federation; `FederationAgent` is its DyKnow Federation service, the proxies
carry agreed streams, and `add_fusion` merges an imported stream with a local one.
`GatewayAgent` is the ACL face of the local DyKnow instance (its content mapping is
`GatewayService`); it lives here, not in `agents`, which knows nothing of DyKnow.
`FoxgloveBridge` serves a platform's view of its federation to Foxglove (docs/foxglove.md).

Each name is imported from its module on first use (a node, ``dyknow node``, never uses
`FoxgloveBridge`): importing the package costs nothing, so the ``dyknow`` entry
(``federation.cli``) holds SIGHUP before any heavy import (``federation._hup``).
"""

from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ._export import Export, ExportProxy
    from ._foxglove import FoxgloveBridge
    from ._fusion import Fusion, add_fusion
    from ._gateway import GATEWAY_SERVICE_TYPE, GatewayAgent, GatewayEnded, GatewayStats
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

_WHERE = {  # each public name: the module it is imported from on first use
    "Export": "._export",
    "ExportProxy": "._export",
    "FoxgloveBridge": "._foxglove",
    "Fusion": "._fusion",
    "add_fusion": "._fusion",
    "GATEWAY_SERVICE_TYPE": "._gateway",
    "GatewayAgent": "._gateway",
    "GatewayEnded": "._gateway",
    "GatewayStats": "._gateway",
    "GatewayRefusal": "._gateway_service",
    "GatewayService": "._gateway_service",
    "Import": "._import",
    "ImportProxy": "._import",
    "DEFAULT_IMPORT_LABEL": "._platform",
    "DfEventLimitSettings": "._platform",
    "FactSettings": "._platform",
    "FederationPlatform": "._platform",
    "FoxgloveSettings": "._platform",
    "KxLimitSettings": "._platform",
    "MqttSettings": "._platform",
    "PlatformConfig": "._platform",
    "PlatformConfigError": "._platform",
    "RateLimitSettings": "._platform",
    "ZenohSettings": "._platform",
    "load_sharing": "._platform",
    "Anchor": "._service",
    "Consent": "._service",
    "Exporter": "._service",
    "FEDERATION_AGENT": "._service",
    "FEDERATION_SERVICE_TYPE": "._service",
    "FederationAgent": "._service",
    "GlobalResult": "._service",
    "ImportAgreements": "._service",
    "LabelSearch": "._service",
    "LabelTranslator": "._service",
    "MembershipEvent": "._service",
    "ONTOLOGY": "._service",
    "StreamExport": "._service",
    "InterfaceSessions": "._sessions",
    "SessionsProvider": "._sessions",
    "TableSessions": "._sessions",
    "Sharing": "._sharing",
    "SharingRule": "._sharing",
    "SharingSettings": "._sharing",
}

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
    "GatewayEnded",
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


if not TYPE_CHECKING:  # to mypy, only the names imported above exist (a typo is an error)

    def __getattr__(name: str) -> Any:
        """A public name, imported from its module on first use (then a plain attribute)."""
        module = _WHERE.get(name)
        if module is None:
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
        value = getattr(import_module(module, __name__), name)
        globals()[name] = value
        return value


def __dir__() -> list[str]:
    """The public names, those imported on first use included."""
    return sorted({*globals(), *__all__})
