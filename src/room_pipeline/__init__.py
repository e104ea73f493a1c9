"""room-pipeline: reproducible CT-to-bronchoscopy dataset simulator (ROOM method)."""

__version__ = "0.1.0"
