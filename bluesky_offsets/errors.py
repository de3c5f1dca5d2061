"""The errors a user can fix.

:class:`InputError` is what the library raises where it refuses its input: a bad option, parameter,
file, measurement or request.  The command line prints it in one line (exit status 2).  Any other
exception is a bug, or a failure the user did not cause, and keeps its traceback.  It is a
``ValueError``, so code that caught the library's refusals as such still does.
"""


class InputError(ValueError):
    """Input the library refuses; the message says what and why."""
