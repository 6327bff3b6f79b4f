"""User-facing errors: one line that names the file or key and the fix."""


class PairedGTAError(RuntimeError):
    """An error caused by input or configuration; printed as one line, exit code 2."""


class ConfigError(PairedGTAError):
    pass


class DataError(PairedGTAError):
    pass


class ModelError(PairedGTAError):
    pass


class RendererError(PairedGTAError):
    pass
