"""Exception hierarchy. The CLI turns any BlocklocError into one line and exit code 2."""


class BlocklocError(Exception):
    """Base of every error a user can cause (bad input, missing data, no match)."""


class ConfigError(BlocklocError):
    """A config file or value is malformed."""


class DatasetError(BlocklocError):
    """A sequence, recording or trajectory file is missing or malformed."""


class MapError(BlocklocError):
    """A map store, tile or block is missing or corrupt."""


class RegistrationError(BlocklocError):
    """Registration inputs are unusable (empty, too few points, NaN)."""


class GlobalInitError(BlocklocError):
    """Global initialization got bad input or found no verified match."""


class TrackingError(BlocklocError):
    """Tracking cannot start or continue."""


class EvaluationError(BlocklocError):
    """Trajectories cannot be evaluated (no overlap, bad files)."""


class SimError(BlocklocError):
    """The simulator got an unusable preset or parameter."""


class OutputWriteError(BlocklocError):
    """An output file could not be written mid-run (disk full, its folder removed, a read-only
    file system): the message names the file and the cause; exit code 1 (the run was valid,
    the machine failed it). What was written before is whole."""

    exit_code = 1

    def __init__(self, path, cause: str, note: str = "") -> None:
        super().__init__(f"{path}: cannot write ({cause})" + (f"; {note}" if note else ""))
        self.path = path
        self.cause = cause

    @classmethod
    def of(cls, path, exc: OSError) -> "OutputWriteError":
        return cls(path, exc.strerror or str(exc))
