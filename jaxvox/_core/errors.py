"""Exception types raised by the host-side API."""


class JaxvoxError(ValueError):
    """Bad input or a result that could not be produced; the message names the problem."""
