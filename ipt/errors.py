"""The root of IPT's exception tree.

Every module raises its own subclass of :class:`IptError` for problems a user can fix (a bad file, a
bad value). The command-line tools catch ``IptError`` and print its message as one line, exit code 2;
anything else is a bug and keeps its traceback.
"""


class IptError(Exception):
    """A problem with the user's input, stated in words the user can act on."""
