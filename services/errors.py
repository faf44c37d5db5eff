"""The one exception type for bad input, shared by the CLI, workers and API."""


class InputError(ValueError):
    """Input that cannot be used, with a message naming the file or field and what is wrong.

    The CLI prints the message and exits non-zero; the API answers 4xx
    ``application/problem+json`` with it. Science functions raise plain
    ``ValueError`` with a full sentence; the code that read the input from a
    file re-raises it as an ``InputError`` that names the file.

    An error about one parameter of a use case names it as the use case does (``parameter``, e.g.
    ``saturation_level``) at the start of the message; the CLI writes the option that sets it instead
    (``--saturation-level``), so a worker's error never names a flag.
    """

    def __init__(self, message: str, *, parameter: str | None = None) -> None:
        super().__init__(message)
        self.parameter = parameter
