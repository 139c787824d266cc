"""Training: value networks of any activation layout learned from the HJI residual.

Skeletal until its issue lands; it will depend on :mod:`reach_envs.systems` only.
"""
