"""Nearest-keyframe search for the rotation-minimised Eq. 4 distance.

:mod:`.keyframe_index` (the staged search), :mod:`.parameters` (its one
parameter object), :mod:`.keyframe_store` (descriptors and keys in memory),
:mod:`.keys` (the small keys and their kernels), :mod:`.selection` (row-wise
smallest-value picks), :mod:`.state` (saved arrays), :mod:`.translation_search`
(the query from nearby viewpoints), :mod:`.sequence_matching` (candidates scored
over the keyframes before the query).
"""
