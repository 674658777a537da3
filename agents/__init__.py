"""Agents: FIPA-ACL speech acts, asyncio agents, protocols, Directory Facilitator, transports."""
