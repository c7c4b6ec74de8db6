"""Error types. Each names the problem so a user can act on it without reading a traceback."""
from __future__ import annotations


class FlowcastError(Exception):
    """Base class of every error flowcast raises on bad input or configuration."""


class ConfigError(FlowcastError):
    """An unknown preset, an invalid value, or an inconsistent combination of options."""


class DatasetError(FlowcastError):
    """A dataset file is missing, damaged, or does not match what the caller expects."""


class CheckpointError(FlowcastError):
    """A model checkpoint is missing, corrupt, or was made for a different configuration."""


class DataSourceError(FlowcastError):
    """Fetching or reading DataSF data failed (network, HTTP status, malformed payload)."""


class ValidationError(DataSourceError):
    """Data were read but violate the schema (missing field, bad value, duplicate date...)."""


class OfflineError(DataSourceError):
    """No network and no cache to fall back on."""


class TrainingDivergedError(FlowcastError):
    """Training produced NaN/inf or diverged; nothing was saved."""


class ModelMissingError(FlowcastError):
    """A model is not in the store where only stored models may be used (nothing is trained)."""
