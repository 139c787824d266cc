"""reach: neural Hamilton-Jacobi reachability.

This package is the base layer every other package builds on, and it imports without Gymnasium:

- :mod:`reach.systems`: one physics definition per dynamical system (Air3D, multi-vehicle Dubins
  cars), from which Hamiltonians and optimal inputs are derived;
- :mod:`reach.value_function`: the ``ValueFunction`` protocol grid solutions and networks share;
- :mod:`reach.atomic`, :mod:`reach.locking`, :mod:`reach.provenance`: atomic writes, run-directory
  locks and the versions recorded in every file;
- :mod:`reach.compiling`, :mod:`reach.validation`: the ``torch.compile`` rule and argument checks;

Data flows one way: ``reach`` (base) -> ``reach_envs`` / ``groundtruth`` -> ``training`` -> ``safety``
(core) -> ``studies`` -> ``reach_cli`` (the command line; ``python -m reach`` runs it).
"""

__version__ = "0.1.0"
