"""One error type for bad input: the CLI prints its message as a single line."""


class MonoMapError(Exception):
    """Bad user input or data (missing file, malformed calib, corrupt checkpoint...).

    The message must name the offending file or option and say what is wrong;
    ``mono-map`` prints it as ``mono-map: error: <message>`` and exits with status 2.
    """
