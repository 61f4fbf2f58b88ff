"""The service: the pipeline from MAVLink input to estimates and back, live or from a file."""

from mavest.service.config import InputConfig, OutputConfig, ServiceConfig
from mavest.service.pipeline import Pipeline, Stream

__all__ = ["InputConfig", "OutputConfig", "Pipeline", "ServiceConfig", "Stream"]
