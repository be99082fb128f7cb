"""A certificate that every deployed Euler step of a stable policy decreases V over a box.

:mod:`~snds.certify.interval` (sound interval arithmetic in NumPy), :mod:`~snds.certify.jets`
(interval Taylor jets), :mod:`~snds.certify.model` (the policy's weights and their jets),
:mod:`~snds.certify.bounds` (the per-cell proof), :mod:`~snds.certify.search` (branch and
bound), :mod:`~snds.certify.certificate` (the file and the search for the largest step) and
:mod:`~snds.certify.recheck` (an independent re-check in Arb ball arithmetic).
"""

__all__: list[str] = []
