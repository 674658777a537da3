"""DyKnow Federation: the federation service, export and import proxies, platform assembly."""
