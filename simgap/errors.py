"""The one exception type users see: every bad input raises a SimgapError naming the problem.

The CLI turns it into ``error: <message>`` and a non-zero exit, never a traceback.
"""


class SimgapError(ValueError):
    """Bad input or an unusable result, with a message that names the problem."""
