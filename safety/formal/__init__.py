"""Formal certificates: sound bounds over boxes of the state space, a safe set closed under a backup
input, written to a file that an independent checker re-verifies. Only these are called certified.

* :mod:`safety.formal.intervals`, :mod:`safety.formal.bounds`, :mod:`safety.formal.linear_bounds` -
  interval arithmetic over the physics and sound bounds of a network over a box;
* :mod:`safety.formal.verifier` - proves ``V >= c`` (or refutes it) box by box, resumably
  (:mod:`safety.formal.progress`);
* :mod:`safety.formal.cover` - the cell grid and covers of boxes the closure looks up;
* :mod:`safety.formal.certificate` - the closure, the certificate file and its checker;
* :mod:`safety.formal.certified_filter` - a filter that keeps a system inside a certificate's set.
"""
