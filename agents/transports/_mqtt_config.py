"""The MQTT transport's settings: where the broker is, how to reach it, its TLS.

Apart from the transport (`agents.transports._mqtt`): every platform's config has a
transport table that may be MQTT's, so these models are imported by every platform; the
transport itself only by one that speaks MQTT.
"""

from __future__ import annotations

import ssl
import uuid
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, model_validator

from .._exceptions import TransportError


def _new_client_id() -> str:
    return f"dyknow-{uuid.uuid4().hex[:16]}"


class MqttTls(BaseModel):
    """TLS to the broker: the CA that signed it, and this client's certificate (mutual TLS).

    With the generated broker config (``deploy/make_hub_configs.py``) the certificate's CN
    is the platform's name and becomes its MQTT user name.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, defer_build=True)

    root_ca_certificate: Path
    certificate: Path | None = None
    private_key: Path | None = None

    @model_validator(mode="after")
    def _pair(self) -> MqttTls:
        if (self.certificate is None) != (self.private_key is None):
            raise ValueError("give both certificate and private_key, or neither")
        return self

    def relative_to(self, base: Path) -> MqttTls:
        """A copy with relative paths resolved against ``base``."""
        update = {
            name: base / value
            for name in ("root_ca_certificate", "certificate", "private_key")
            if isinstance(value := getattr(self, name), Path) and not value.is_absolute()
        }
        return self.model_copy(update=update)

    def context(self) -> ssl.SSLContext:
        """The client's SSL context; TransportError naming the file that cannot be read."""
        try:
            ctx = ssl.create_default_context(cafile=str(self.root_ca_certificate))
        except (OSError, ssl.SSLError) as exc:
            raise TransportError(
                f"tls.root_ca_certificate: {self.root_ca_certificate}: {exc}"
            ) from exc
        if self.certificate is not None and self.private_key is not None:
            try:
                ctx.load_cert_chain(str(self.certificate), str(self.private_key))
            except (OSError, ssl.SSLError) as exc:
                raise TransportError(
                    f"tls.certificate/private_key: {self.certificate}: {exc}"
                ) from exc
        return ctx


class MqttConfig(BaseModel):
    """Where the MQTT broker is and how to talk to it; validated once, errors name the field."""

    model_config = ConfigDict(extra="forbid", frozen=True, defer_build=True)

    host: str = Field(default="127.0.0.1", min_length=1)
    port: int = Field(default=1883, ge=1, le=65535)
    client_id: str = Field(
        default_factory=_new_client_id,
        pattern=r"^[A-Za-z0-9_.-]{1,40}$",
        description=(
            "The prefix of every connection's client id; each connection adds 64 random "
            "bits, so no other client can take its id over (and evict it)."
        ),
    )
    username: str | None = None
    password: SecretStr | None = None
    keepalive: int = Field(
        default=60,
        ge=1,
        le=65535,
        description="Seconds; the broker declares a silent client dead after 1.5 x this.",
    )
    qos: Literal[0, 1, 2] = Field(default=0, description="QoS of publications and queries.")
    connect_timeout: float = Field(default=10.0, gt=0)
    tls: MqttTls | None = None
    serve_timeout: float = Field(
        default=10.0,
        gt=0,
        description="Seconds a query handler may run before the query gets an error reply.",
    )
    retained_quiet: float = Field(
        default=0.0,
        ge=0,
        le=10,
        description=(
            "Seconds without a retained message, after the round trip, that end a presence "
            "history's replay; 0: the round trip alone (a broker sending retained first)."
        ),
    )

    def relative_to(self, base: str | Path) -> MqttConfig:
        """A copy whose TLS files are resolved against ``base`` (a config file's directory)."""
        if self.tls is None:
            return self
        return self.model_copy(update={"tls": self.tls.relative_to(Path(base))})

    @model_validator(mode="after")
    def _credentials(self) -> MqttConfig:
        if self.password is not None and self.username is None:
            raise ValueError("password: given without a username")
        return self
