"""The one exception type users see: every bad input raises a SimgapError naming the problem.

The CLI turns it into ``error: <message>`` and a non-zero exit, never a traceback.
"""


class SimgapError(ValueError):
    """Bad input or an unusable result, with a message that names the problem."""


def _bad_file_errors() -> tuple:
    import zipfile
    import zlib
    return (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error)


#: what reading a truncated or corrupt .npz / JSON file raises (np.load, zipfile, json):
#: loaders catch these and raise a SimgapError naming the file
BAD_FILE_ERRORS = _bad_file_errors()
