"""The echo agent the multi-process tests run on their member platform."""

from __future__ import annotations

from agents import Agent, ServiceDescription


class ProtectedEcho(Agent):
    """The agent ``echo``, offering a protected ``echo`` service; subclasses answer it."""

    def __init__(self) -> None:
        super().__init__("echo")

    async def setup(self) -> None:
        """Protected: uav-a reaches it through the Interface Agent."""
        assert self.platform.df is not None
        await self.platform.df.register(
            ServiceDescription(name="echo", type="echo", provider=self.aid, visibility="protected")
        )
