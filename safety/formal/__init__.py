"""Formal certificates: sound bounds over boxes of the state space, a safe set closed under a backup
input, written to a file that an independent checker re-verifies. Only these are called certified.

* :mod:`safety.formal.intervals`, :mod:`safety.formal.bounds`, :mod:`safety.formal.linear_bounds` -
  interval arithmetic over the physics and sound bounds of a network over a box;
* :mod:`safety.formal.settings` - what a proof is asked (``CertifySettings``) and what it found
  (``CertificationResult``);
* :mod:`safety.formal.verifier` - proves ``V >= c`` (or refutes it) box by box, resumably
  (:mod:`safety.formal.progress`);
* :mod:`safety.formal.cover` - the cell grid and covers of boxes the closure and the checker look up;
* :mod:`safety.formal.closure` - the largest union of boxes closed under a backup input: the certified set;
* :mod:`safety.formal.certificate` - the certificate and its file;
* :mod:`safety.formal.checker` - re-verifies a certificate file from the file alone;
* :mod:`safety.formal.certified_filter` - a filter that keeps a system inside a certificate's set.
"""
