"""Statistical verification: closed-loop rollouts of the induced policy and the scenario bounds on them.

A scenario bound says, with confidence ``1 - beta``, that at most a share ``eps`` of the states of a
set fail under the named policy. It is a statistical guarantee, never called "certified" (that word
belongs to :mod:`safety.formal`).

* :mod:`safety.verification.rollout` - batched closed-loop simulation that skips decided trajectories;
* :mod:`safety.verification.rollout_store` - outcomes kept block by block, so a long run resumes;
* :mod:`safety.verification.verify` - violation statistics, delta level and the scenario set;
* :mod:`safety.verification.metrics` - Wilson intervals and the scenario ``eps``;
* :mod:`safety.verification.sharding` - independent blocks of states over Ray.
"""
