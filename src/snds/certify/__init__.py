"""A certificate that every deployed Euler step of a stable policy decreases V over a box.

The search: :mod:`~snds.certify.interval` (sound interval arithmetic in NumPy),
:mod:`~snds.certify.affine` and :mod:`~snds.certify.quadratic` (Taylor models),
:mod:`~snds.certify.jets` (forward-mode jets), :mod:`~snds.certify.model` (the policy's
weights and their bounds), :mod:`~snds.certify.bounds` (one cell's proof),
:mod:`~snds.certify.search` (branch and bound) and :mod:`~snds.certify.certificate` (the file).
The re-check, sharing none of the search's bound code: :mod:`~snds.certify.recheck`, on
:mod:`~snds.certify.retaylor` and :mod:`~snds.certify.reprove` (Taylor models with interval
coefficients) and :mod:`~snds.certify.arb` (Arb balls, python-flint).
"""

__all__: list[str] = []
