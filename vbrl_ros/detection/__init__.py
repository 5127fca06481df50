"""Loop-closure detection without ROS: keyframes in, verified closures out.

:mod:`.detector` (the per-keyframe pipeline), :mod:`.database` (the keyframes
remembered) and :mod:`.database_file` (its file), :mod:`.registration`
(geometric verification with KISS-ICP).
"""
