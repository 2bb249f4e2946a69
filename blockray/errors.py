"""Errors a user can cause. The CLI prints them as one line and exits with status 2."""


def printable(text, limit=None):
    """``text`` with control and other non-printable characters escaped, so a message stays one
    line and cannot drive the terminal; cut to ``limit`` characters (ending in ``...``)."""
    text = str(text)
    if limit is not None and len(text) > limit:
        text = text[:max(limit - 3, 1)] + "..."
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


#: brackets a parameter's name in a message (:func:`option`); never in text shown through
#: :func:`printable`, which escapes control characters
_OPTION = "\x1f"


def option(name):
    """The parameter ``name`` inside an error's message. A library caller reads ``name`` (the
    parameter of the function or options object it set); the CLI prints the command-line option
    that sets it (``--name``; host_driver/cli.py spells the exceptions)."""
    return f"{_OPTION}{name}{_OPTION}"


def spell(text, name):
    """``text`` with each :func:`option` in it written as ``name(parameter)``."""
    parts = str(text).split(_OPTION)
    return "".join(name(part) if k % 2 else part for k, part in enumerate(parts))


class Spelled:
    """An exception or warning whose message (the first argument, kept as given so it survives
    pickling to and from a cluster's workers) may name parameters with :func:`option`; ``str()``
    shows their names, :meth:`spelled` any other spelling."""

    def __str__(self):
        return spell(super().__str__(), str)

    def spelled(self, name):
        """The message with each parameter written as ``name(parameter)``."""
        return spell(super().__str__(), name)


class BlockrayError(Spelled, Exception):
    """Base class of every error caused by bad input or impossible parameters."""


class SceneError(BlockrayError):
    """A scene file is unreadable or malformed. The message names the file and line."""

    def __init__(self, message, *, path=None, line=None):
        self.path = path
        self.line = line
        where = ""
        if path is not None:
            shown = printable(path, 200)        # a file name may hold a newline or escapes
            where = f"{shown}:{line}: " if line is not None else f"{shown}: "
        super().__init__(f"{where}{message}")


class ParameterError(BlockrayError):
    """A parameter (command-line option or hardware parameter) is out of range or inconsistent.

    The message names the parameter; ``parameter`` holds its name where one parameter is at
    fault, so the CLI can name the option that set it.
    """

    def __init__(self, message, *, parameter=None):
        self.parameter = parameter
        super().__init__(message)


class SolveError(BlockrayError):
    """A solve went wrong: a form factor that is not a finite number >= 0, a shooter whose factors
    deliver more light than it has, or a radiosity or residual that diverges. The message names
    the patch; ``patch`` holds it (None if no one patch is at fault)."""

    def __init__(self, message, *, patch=None):
        self.patch = patch
        super().__init__(message)


class ResourceError(BlockrayError):
    """The machine refuses a resource a run needs (memory under a ulimit); the message names the
    tool and the resource."""


class ToolError(BlockrayError):
    """An external tool (Yosys, nextpnr, ecppll, ecppack) failed; the message names the tool, its
    exit status, its last error line and its log."""


class CapacityError(BlockrayError):
    """A scene does not fit the chosen widths or memories."""
