"""How every ExClone operator tells the user why it stopped (one line, nothing changed) or why
it cannot run (the button's tooltip, through poll_message_set)."""
import functools

from ..core.errors import Cancelled, ExCloneError, user_message


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


def in_object_mode(cls, context):
    """A poll's Object Mode check, with the reason when it fails."""
    if context.mode != 'OBJECT':
        cls.poll_message_set("Switch to Object Mode first")
        return False
    return True


def passes(cls, check, *args):
    """A poll's check(*args): True, or False with the ExCloneError's message as the reason."""
    try:
        check(*args)
    except ExCloneError as exc:
        cls.poll_message_set(str(exc))
        return False
    return True
