"""The exit statuses of ``reach`` and of the study scripts, one place for every command line to share.

In the base layer because the studies return them too (a study stage that diverged or failed in part
returns :data:`EXIT_PARTIAL`), and the command line sits above the studies."""

from __future__ import annotations

#: a command that did all its work
EXIT_OK = 0
#: a bug, not bad input (one line naming the error; ``--debug`` shows the traceback)
EXIT_INTERNAL = 1
#: exit status of an expected failure (bad input, unreadable file), as argparse uses for usage errors
EXIT_USAGE = 2
#: exit status when the command ran but part of its work failed: a source of ``reach evaluate`` that
#: did not load or verify (its row says why), a training run that diverged (its last good checkpoint
#: is kept); what did succeed is written
EXIT_PARTIAL = 3
#: exit status after SIGINT/SIGTERM (128 + SIGINT), as shells report it
EXIT_INTERRUPTED = 130
#: exit status when the reader of the output went away (128 + SIGPIPE), e.g. ``reach envs | head -1``
EXIT_BROKEN_PIPE = 141


__all__ = ["EXIT_BROKEN_PIPE", "EXIT_INTERNAL", "EXIT_INTERRUPTED", "EXIT_OK", "EXIT_PARTIAL", "EXIT_USAGE"]
