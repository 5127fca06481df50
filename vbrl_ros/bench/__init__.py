"""``vbrl bench``'s measurements: :mod:`.speed_targets` (featurizer, solver), :mod:`.solver`,
:mod:`.index` (the keyframe index at scale) on :mod:`.descriptors`."""
