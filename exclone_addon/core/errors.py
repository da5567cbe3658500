"""Errors whose message is written for the user (operator report or one-line CLI exit)."""


class ExCloneError(ValueError):
    """Bad input or a result that cannot be trusted; str(error) says what is wrong."""


class Cancelled(Exception):
    """Raised from a progress callback to stop a long run; nothing is written."""
