"""What ``vbrl_node`` checks and opens before it takes a cloud: its parameters, topics and database.

Each check stops the start with one line naming the parameter (:class:`SettingsError`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node

from vbrl_ros.detection.database import KeyframeDatabase
from vbrl_ros.detection.settings import SettingsError
from vbrl_ros.io.atomic import check_writable, remove_stale_temporaries
from vbrl_ros.model.model_file import VBRLModel
from vbrl_ros.ros.settings import DESCRIPTIONS, NodeSettings, index_parameters, unknown_parameters
from vbrl_ros.ros.startup import rcl_error_line

#: The parameters that name a topic (odom_topic may be empty: no odometry).
TOPIC_PARAMETERS = ("cloud_topic", "odom_topic", "loop_closure_topic", "lio_sam_topic", "markers_topic")


def read_settings(node: Node) -> NodeSettings:
    """Declare every parameter and read it; refuse a name no one declared."""
    values = {}
    for name, default in NodeSettings.defaults().items():
        # dynamic typing: a wrongly typed value reaches our validation,
        # which names the parameter, instead of an rclpy type exception
        descriptor = ParameterDescriptor(description=DESCRIPTIONS[name], dynamic_typing=True)
        node.declare_parameter(name, default, descriptor)
        values[name] = node.get_parameter(name).value
    refuse_unknown_overrides(node)
    return NodeSettings.from_values(values)


def refuse_unknown_overrides(node: Node) -> None:
    """Stop on a -p or parameter-file name that no one declared.

    rclpy drops such overrides silently, so a misspelled ``cloud_topics``
    would leave a robot running on the default topic with nothing said.
    What rclpy declares itself (use_sim_time, ...) counts as known. The
    overrides are rclpy's protected ``Node._parameter_overrides``: it has
    no public way to list them without declaring them all.
    """
    unknown = [name for name in node._parameter_overrides if not node.has_parameter(name)]
    if unknown:
        raise SettingsError(unknown_parameters(sorted(unknown)))


def check_topics(node: Node, settings: NodeSettings) -> None:
    """Stop on a topic name rclpy would refuse (its exception names neither the parameter
    nor, in one line, the problem)."""
    for name in TOPIC_PARAMETERS:
        topic = getattr(settings, name)
        if name == "odom_topic" and not topic:
            continue
        try:
            node.resolve_topic_name(topic)
        except RuntimeError as error:  # rcl's RCLError
            reason = rcl_error_line(error).removeprefix("failed to resolve name: ")
            raise SettingsError(f"parameter '{name}' is not a valid topic name: {topic!r} ({reason})") from None


def check_database_path(settings: NodeSettings) -> None:
    """Stop now if the database cannot be saved, not with every save failing later."""
    path = settings.database_path
    if path:
        try:
            check_writable(path)
        except OSError as error:
            raise SettingsError(f"parameter 'database_path': cannot write {path} "
                                f"({error.strerror}: {error.filename})") from None


def open_database(model: VBRLModel, settings: NodeSettings, log: Callable[[str], None]) -> KeyframeDatabase:
    """The database at ``database_path``, or a new one; ``log`` says what a start cleaned up."""
    scorer = model.scorer(prune=settings.weight_prune)
    model_id = model.identity()
    path = settings.database_path
    if path:
        removed = remove_stale_temporaries(path)
        if removed:
            log(f"removed {len(removed)} temporary file(s) that interrupted saves of {path} left")
    if path and Path(path).exists():
        # a saved database keeps its own storage type and search (and refuses another prune)
        return KeyframeDatabase.load(path, scorer, model_id)
    try:
        return KeyframeDatabase(scorer, model_id, index_parameters(settings))
    except ValueError as error:  # a bound that depends on the model's descriptor
        name = str(error).split()[0]
        raise SettingsError(f"parameter 'index_{name}' for this model: {error}") from None
