"""One lock for reading ``.npy`` arrays (an ``.npz``'s included) in this process.

numpy parses each array's header with ``ast.literal_eval``, and the CPython this project
runs (3.11) keeps the AST constructor's recursion depth in the interpreter's state, shared
by its threads: when a garbage collection inside one thread's parse runs Python code
(a finalizer) and another thread parses meanwhile, one of them fails with "SystemError:
AST constructor recursion depth mismatch". Seen once in the suite: a viewer's
``/v1/demo/animation`` answered 500 while another request of the same server loaded a rig
in another thread; four threads parsing a header in a loop beside cyclic garbage with
finalizers failed 503 times in 20 s. Every array read in ``facecast.rig`` holds this lock
for its whole read, headers and data (the largest files read, rigs, are ~20 MB: reads wait
for each other, frames never do).
"""

from __future__ import annotations

import threading

__all__ = ["NPY_READS"]

#: Held while an ``np.load`` (and, for an ``.npz``, the reads of its arrays) runs.
NPY_READS = threading.RLock()
