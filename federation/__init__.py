"""DyKnow Federation: the federation service, export and import proxies, fusion, platform assembly.

`FederationPlatform` (configured by a `PlatformConfig`, usually a TOML file) is one
member of a federation; `FederationAgent` is its DyKnow Federation service, the proxies
carry agreed streams, and `add_fusion` merges an imported stream with a local one.
`GatewayAgent` is the ACL face of the local DyKnow instance (its content mapping is
`GatewayService`); it lives here, not in `agents`, which knows nothing of DyKnow.
`FoxgloveBridge` serves a platform's view of its federation to Foxglove (docs/foxglove.md).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ._export import Export, ExportProxy
    from ._foxglove import FoxgloveBridge
    from ._fusion import Fusion, add_fusion
    from ._gateway import GATEWAY_SERVICE_TYPE, GatewayAgent, GatewayStats
    from ._gateway_service import GatewayRefusal, GatewayService
    from ._import import Import, ImportProxy
    from ._platform import (
        DEFAULT_IMPORT_LABEL,
        FederationPlatform,
        FoxgloveSettings,
        KxLimitSettings,
        MqttSettings,
        PlatformConfig,
        PlatformConfigError,
        RateLimitSettings,
        ZenohSettings,
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

# name -> the module defining it, imported on first use: a process that needs one part (an
# agent platform using only the gateway) does not load the others (export, Foxglove, …)
_WHERE = {
    "Anchor": "_service",
    "Consent": "_service",
    "DEFAULT_IMPORT_LABEL": "_platform",
    "Export": "_export",
    "ExportProxy": "_export",
    "Exporter": "_service",
    "FEDERATION_AGENT": "_service",
    "FEDERATION_SERVICE_TYPE": "_service",
    "FederationAgent": "_service",
    "FederationPlatform": "_platform",
    "FoxgloveBridge": "_foxglove",
    "FoxgloveSettings": "_platform",
    "Fusion": "_fusion",
    "GATEWAY_SERVICE_TYPE": "_gateway",
    "GatewayAgent": "_gateway",
    "GatewayRefusal": "_gateway_service",
    "GatewayService": "_gateway_service",
    "GatewayStats": "_gateway",
    "GlobalResult": "_service",
    "Import": "_import",
    "ImportAgreements": "_service",
    "ImportProxy": "_import",
    "InterfaceSessions": "_sessions",
    "KxLimitSettings": "_platform",
    "LabelSearch": "_service",
    "LabelTranslator": "_service",
    "MembershipEvent": "_service",
    "MqttSettings": "_platform",
    "ONTOLOGY": "_service",
    "PlatformConfig": "_platform",
    "PlatformConfigError": "_platform",
    "RateLimitSettings": "_platform",
    "SessionsProvider": "_sessions",
    "Sharing": "_sharing",
    "SharingRule": "_sharing",
    "SharingSettings": "_sharing",
    "StreamExport": "_service",
    "TableSessions": "_sessions",
    "ZenohSettings": "_platform",
    "add_fusion": "_fusion",
}


def __getattr__(name: str) -> Any:
    """A public name, its module imported the first time it is asked for."""
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    """The public names, loaded or not."""
    return sorted(set(globals()) | set(__all__))


__all__ = [
    "DEFAULT_IMPORT_LABEL",
    "FEDERATION_AGENT",
    "FEDERATION_SERVICE_TYPE",
    "GATEWAY_SERVICE_TYPE",
    "ONTOLOGY",
    "Anchor",
    "Consent",
    "Export",
    "ExportProxy",
    "Exporter",
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
]
