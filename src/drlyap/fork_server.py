"""Imported first by the fork server that starts the local proof workers (:mod:`drlyap.parallel`): the server then
ends the moment the process that started it ends, also while it still imports torch (it would otherwise finish that
first, seconds later). Only the kernel's request, no watching thread: the server forks.

:data:`SERVER` is the server's pid, and so, in a process it forked, the parent to bind to: read there, it cannot be
the pid of whatever adopted the process after the server ended, as ``os.getppid()`` read late can.
"""

import os

from drlyap.lifeline import die_with_parent

die_with_parent(os.getppid())
SERVER = os.getpid()
