"""Exceptions that carry what went wrong, where, and what was expected."""


class KeoError(Exception):
    """Root of keo's own errors."""


class ConfigError(KeoError):
    """A config file or a command-line argument is wrong; the CLI exits with code 2.

    Args:
        source: the config file (or "command line").
        key: the key or argument that is wrong, e.g. "timing.delay_s" or "--gain".
        message: what is wrong with it and what would be accepted.
    """

    def __init__(self, source: str, key: str, message: str) -> None:
        self.source = source
        self.key = key
        self.message = message
        super().__init__(f"{source}: key '{key}': {message}")


class DataFormatError(KeoError):
    """An input file is not in the interchange format; the CLI exits with code 2.

    Args:
        path: the file.
        line: the line number (1 for the header; 0 for the file as a whole).
        column: the column that is wrong or missing ("-" for none in particular).
        message: what is wrong with it.
    """

    def __init__(self, path: str, line: int, column: str, message: str) -> None:
        self.path = path
        self.line = line
        self.column = column
        super().__init__(f"{path}:{line}: column '{column}': {message}")
