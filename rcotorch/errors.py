"""Exceptions raised by rcotorch. Each names the block, port, file, row or shape at fault."""


class RcoError(Exception):
    """Base class of every rcotorch error."""


class PortError(RcoError, KeyError):
    """An unknown, missing or doubly connected port."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return str(self.args[0]) if self.args else ""


class DimensionError(RcoError, ValueError):
    """A tensor or port has the wrong shape."""


class AlgebraicLoopError(RcoError, ValueError):
    """Direct-feedthrough paths form a cycle, so a step cannot be ordered."""


class ConfigError(RcoError, ValueError):
    """A setting has a bad value (name, range or type)."""


class SettingError(ConfigError):
    """A scenario's setting, or the settings of a run together, refused: ``settings`` names them (a command line
    names the options that gave them); ``detail`` says what is wrong without naming their values again."""

    def __init__(self, message: str, settings: tuple[str, ...] = (), detail: str | None = None):
        super().__init__(message)
        self.settings = tuple(settings)
        self.detail = message if detail is None else detail


class DataError(RcoError, ValueError):
    """Recorded data is missing, malformed or non-finite."""


class OutputError(RcoError, OSError):
    """An output folder cannot be used: it is a file or a broken symbolic link, not writable, in use by another
    process, or it holds results this run did not write; or writing to it failed (a full disk), or it was
    deleted or replaced during the run."""


class CheckpointError(RcoError, ValueError):
    """A checkpoint is missing, truncated, corrupted, or does not match what a resume asks for."""


class FolderInUseError(OutputError):
    """Another run (in this or another process) holds the output folder's lock."""
