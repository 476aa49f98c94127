"""The estimator as a separate zenoh process: protocol, sessions, server."""

from estimator_service.service.protocol import PROTOCOL_VERSION, ProtocolError
from estimator_service.service.server import EstimatorService, ServiceConfig, main, zenoh_config

__all__ = [
    "PROTOCOL_VERSION",
    "EstimatorService",
    "ProtocolError",
    "ServiceConfig",
    "main",
    "zenoh_config",
]
