"""The learned model: its file, its Eq. 4 distance, the solver that learns W.

:mod:`.model_file` (the ``.npz`` and :class:`~vbrl_ros.model.model_file.VBRLModel`),
:mod:`.builtin` (loading the model the package ships), :mod:`.scoring` and
:mod:`.distance_kernels` (the weighted L1 distance), :mod:`.sector_shift`
(yaw of a sector shift), :mod:`.solver` and :mod:`.gram` (Eq. 3 by IRLS),
:mod:`.solver_reference` (Algorithm 1 as written, for tests and the bench).
"""
