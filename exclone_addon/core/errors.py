"""Errors whose message is written for the user (operator report or one-line CLI exit)."""


class ExCloneError(ValueError):
    """Bad input or a result that cannot be trusted; str(error) says what is wrong."""


class Cancelled(Exception):
    """Raised from a progress callback to stop a long run; nothing is written."""


def user_message(error):
    """The one line a user is shown for an exception: an ExCloneError's own words, anything else
    (a bug, never the user's fault) named as an internal error."""
    text = " ".join(str(error).split())
    if isinstance(error, ExCloneError):
        return text
    return f"internal error ({type(error).__name__}: {text})"
