"""How every ExClone operator tells the user that it stopped: one line, nothing changed."""
import functools

from ..core.errors import Cancelled, user_message


def failed(operator, error, about=None):
    """Report an exception as the operator's one line; {'CANCELLED'}."""
    if isinstance(error, Cancelled):
        operator.report({'WARNING'}, "Cancelled; nothing was changed")
    else:
        message = user_message(error)
        operator.report({'ERROR'}, f"{about}: {message}" if about else message)
    return {'CANCELLED'}


def reporting(execute):
    """An operator's execute(self, context) whose every exception is reported as one line."""
    @functools.wraps(execute)
    def execute_reporting(self, context):
        try:
            return execute(self, context)
        except Exception as exc:   # a bug too: one line, never a traceback in the user's face
            return failed(self, exc)
    return execute_reporting
