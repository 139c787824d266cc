"""Safety: optimal policies from grad V, least-restrictive safety filters, rollouts and verification.

Skeletal until its issue lands; it will depend on :mod:`reach_envs.systems` and value functions,
never the other way round.
"""
