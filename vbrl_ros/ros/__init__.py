"""Everything that talks ROS 2: the only package that imports rclpy or message packages.

:mod:`.node` (``vbrl_node``: start and stop), :mod:`.startup` (its ``--help`` and
command-line checks), :mod:`.detector_node` (the ROS node), :mod:`.settings` (its
parameters), :mod:`.odometry` (checked poses and keyframe spacing),
:mod:`.messages` (loop-closure messages), :mod:`.outputs` (diagnostics and
markers), :mod:`.bag_player` and :mod:`.message_conversion` (``vbrl replay``),
:mod:`.testing` and :mod:`.online_session` (isolated DDS for tests and the demo).
"""
