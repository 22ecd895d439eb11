"""The one exception type that udh raises for problems a user can fix.

The library raises :class:`UdhError` with a one-line message that says what is wrong and what to do;
only the CLI turns it into a message on stderr and a non-zero exit code.
"""


class UdhError(Exception):
    """A problem with the user's input or environment, with a one-line, actionable message."""


class EstimationFailed(UdhError):
    """An estimator could not produce a trustworthy homography for a pair (too few matches, divergence)."""
