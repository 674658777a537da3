"""DyKnow Federation: the federation service, export and import proxies, platform assembly."""

from ._proxies import (
    Export,
    ExportProxy,
    Import,
    ImportProxy,
    InterfaceSessions,
    SessionsProvider,
    TableSessions,
)

__all__ = [
    "Export",
    "ExportProxy",
    "Import",
    "ImportProxy",
    "InterfaceSessions",
    "SessionsProvider",
    "TableSessions",
]
