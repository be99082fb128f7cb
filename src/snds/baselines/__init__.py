"""Baselines the benchmark compares SNDS with, each a :class:`~snds.policy.Policy` and a
:class:`~snds.methods.Method`.

* :mod:`snds.baselines.lpvds`: LPV-DS (Figueroa & Billard, CoRL 2018), a Gaussian-mixture
  blend of linear systems with one shared quadratic Lyapunov function: a physically-consistent
  mixture, P estimated from the data, then the linear systems by a convex program (its steps
  in :mod:`snds.baselines.lpvds_mixture` and :mod:`snds.baselines.lpvds_programs`).
* :mod:`snds.baselines.seds`: SEDS (Khansari-Zadeh & Billard, T-RO 2011), Gaussian mixture
  regression whose every component is a stable linear system.
* :mod:`snds.baselines.sdsef`: SDS-EF (Rana et al., L4DC 2020), a learned diffeomorphism
  (coupling layers on random Fourier features) that pulls back a linear latent system.

Their optional dependencies (scikit-learn, cvxpy) are imported only when a fit runs
(``pip install 'snds[baselines]'``); loading and evaluating a saved model needs neither.
"""

__all__: list[str] = []
