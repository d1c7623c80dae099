"""One session on the ROS domain: the sequencer refuses (exit 3) when another node
commands the arm or offers the Estimate service it calls. Two sessions on one
domain (other folders, so no lock between them) drove each other's arms, and
another session's estimator answered a session's request."""

from __future__ import annotations

import os
import time

from laser_calib_nodes import common, parameters


# s from a sequencer's start in which it watches the graph for a second commander or Estimate server (the
# default of its owner_watch parameter):
# just made, it had seen none of two running servers, then one before the other; on CI's loaded
# machine, 1.6 s after its start, it had not yet seen another session's sequencer measuring
DISCOVERY = 3.0
# s a publisher's node name is awaited once the publisher is seen (named_publishers)
NAMING = 2.0
# rmw_dds_common's name for a node whose discovery data has not arrived yet
UNKNOWN_NAME = "_NODE_NAME_UNKNOWN_"
UNNAMED = "a node not yet named in the ROS graph"


def declare(node) -> float:
    """The sequencer's owner_watch parameter (s): how long from its start it watches the graph."""
    return parameters.declare(node, "owner_watch", DISCOVERY, "Watch the ROS graph this long from the start, s, "
                              "for another session's sequencer or Estimate server on the domain before the arm moves "
                              "(discovery takes time: longer on a large or loaded network).",
                              rule=parameters.non_negative)


def watch(node, until: float) -> None:
    """NodeError (exit 3) when another node commands the arm or offers the Estimate service too,
    watching the graph until ``until`` (monotonic s): discovery takes time, and a session that
    looked once measured on (DISCOVERY). A stop ends the watch (the measuring loop then stops)."""
    while True:
        commander(node), estimator(node)
        if time.monotonic() >= until or node.stopping.is_set():
            return
        time.sleep(0.1)


def commander(node) -> None:
    """NodeError (exit 3) when another node publishes on the arm's trajectory topic: a second
    sequencer (another session on this ROS domain) or a teleoperation drives the arm too. Each
    session then blamed the arm for not settling where it sent it, or measured on without a word."""
    topic = node.resolve_topic_name(common.JOINT_TRAJECTORY)
    publishers = named_publishers(node, topic, time.monotonic() + NAMING)
    if node.get_fully_qualified_name() in publishers:   # this node's one; a second session's may share its name
        publishers.remove(node.get_fully_qualified_name())
    if publishers:
        others = sorted(set(publishers))
        raise parameters.NodeError(f"{', '.join(others)} also commands the arm on {topic}: two nodes would drive it "
                                   f"(a second session on ROS_DOMAIN_ID {os.environ.get('ROS_DOMAIN_ID', '0')}?); "
                                   "give each session its own domain or namespace (the launch files' namespace:=)", 3)


def named_publishers(node, topic: str, until: float) -> list[str]:
    """The fully qualified names of the nodes publishing on ``topic``. DDS may announce a
    publisher before its node's name (rmw's graph cache then says _NODE_NAME_UNKNOWN_, as CI's
    refusal printed): the names are awaited until ``until`` (monotonic s), and one still unknown
    is called what it is."""
    while True:
        infos = node.get_publishers_info_by_topic(topic)
        if all(info.node_name != UNKNOWN_NAME for info in infos) or time.monotonic() >= until:
            return [UNNAMED if info.node_name == UNKNOWN_NAME else f"{info.node_namespace.rstrip('/')}/{info.node_name}"
                    for info in infos]
        time.sleep(0.05)


def estimator(node) -> None:
    """NodeError (exit 3) when more than one node offers the Estimate service the sequencer calls:
    another session's estimator on this ROS domain answered a session's request (the fastest
    server wins) with its own robot and sigmas, while the session's own wrote its report into the
    folder: the console and the files disagreed, without a word. Checked at the start, before the
    arm moves, and again before the call."""
    if node.end.mode != "service":
        return
    name = node.resolve_service_name(common.ESTIMATE_SERVICE)
    if (servers := node.count_services(name)) > 1:
        raise parameters.NodeError(f"{servers} nodes offer the Estimate service on {name}: either could answer this "
                                   f"session (another session's estimator on ROS_DOMAIN_ID "
                                   f"{os.environ.get('ROS_DOMAIN_ID', '0')}?); give each session its own domain or "
                                   "namespace (the launch files' namespace:=)", 3)
