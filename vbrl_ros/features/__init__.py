"""The per-voxel VBRL features of a scan and the descriptor layout.

:mod:`.featurizer` (descriptor and layout), :mod:`.kernels` (the compiled
one-pass accumulation), :mod:`.hog` (histograms of oriented gradients).
"""
