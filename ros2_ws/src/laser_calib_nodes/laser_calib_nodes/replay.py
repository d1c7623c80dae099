"""replay: republish a recorded session's topics with their original timing.

    replay BAG [--rate R] [--topics T ...] [--exclude T ...] [--wait-for T ...]

Motion commands (joint_trajectory) are left out unless named in --topics:
replayed, they would move a live arm on the same domain. Messages go out as
recorded (raw CDR, same types, same QoS as offered at recording, header stamps
untouched) at the bag's receive times, scaled by
1/R. With --wait-for, playback starts once each named topic's publisher has
matched a subscriber (so nothing is published into the void); without it, messages that went out
while their topic had no subscriber are counted in a warning. An estimator listening to
the replayed samples computes what it computed live.

``main(argv)`` is the entry point of the `replay` executable and of
`laser-calib replay` (the core command line calls it when rclpy is available).
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
import time
from collections import Counter
from itertools import chain

import rclpy
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from laser_calib.cli.arguments import add_replay_arguments
from laser_calib.io.errors import InputError

from laser_calib.io import bag
from laser_calib_nodes.common import ROS_ARGUMENT_ERRORS, rcl_error_line
from laser_calib_nodes.shutdown import die_with_parent


def message_class(msgtype: str):
    package, kind, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ImportError, AttributeError):
        raise InputError(msgtype, "message type not available here (build or source the workspace)") from None


def qos_of(profiles) -> QoSProfile:
    if not profiles:
        return QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    p = profiles[0]
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=max(int(p.depth), 100),
        reliability=ReliabilityPolicy.BEST_EFFORT if p.reliability.name == "BEST_EFFORT" else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if p.durability.name == "TRANSIENT_LOCAL" else
        DurabilityPolicy.VOLATILE)


# Message types that move hardware: left out unless named in --topics
COMMANDS = ("trajectory_msgs/msg/JointTrajectory",)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="replay", description="Republish a recorded calibration session.")
    add_replay_arguments(parser)
    return parser


def absolute(topic: str) -> str:
    return topic if topic.startswith("/") else "/" + topic


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ros_args = []
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        argv, ros_args = argv[:i], argv[i:]
    args = build_parser().parse_args(argv)
    # a bag names its topics absolute (/samples); a name given as a node would resolve it (samples) is the same
    args.topics, args.exclude, args.wait_for = ([absolute(t) for t in names] if names is not None else None
                                                for names in (args.topics, args.exclude, args.wait_for))
    try:
        with bag.intact_parts(args.bag) as (parts, lost):
            return replay(args, ros_args, parts, lost)
    except InputError as exc:  # no segment of the bag opens
        print(f"replay: {exc}", file=sys.stderr)
        return 2


def replay(args: argparse.Namespace, ros_args: list[str], parts: list, lost: list[str]) -> int:
    """Play ``parts`` (bag.intact_parts) in turn; the damaged segments ``lost`` are said, as estimate --bag
    says them, and the others played (a bag with one segment lost was refused whole)."""
    for segment in lost:
        print(f"replay: warning: {args.bag}: segment {segment} is damaged and skipped: its messages are not "
              "replayed", file=sys.stderr, flush=True)
    try:
        topics = {}
        for part in parts:
            for topic, (kind, count, profiles) in bag.bag_topics(part).items():
                topics[topic] = (kind, topics.get(topic, (kind, 0))[1] + count, profiles)
        chosen = {t: v for t, v in topics.items()
                  if (t in args.topics if args.topics else v[0] not in COMMANDS) and t not in args.exclude}
        # said when left out by default; topics named (--topics) or excluded were the user's choice
        commands = [t for t, v in topics.items() if v[0] in COMMANDS and t not in chosen and t not in args.exclude
                    and args.topics is None]
        # an --exclude misspelt would replay what the user meant to keep off the domain (a live arm's states)
        missing = [t for t in (args.topics or []) + args.exclude + args.wait_for if t not in topics]
        if missing:
            raise InputError(args.bag, f"no topic {missing[0]} in the bag (it has {', '.join(sorted(topics))})")
        if not chosen:
            raise InputError(args.bag, "no topic left to replay (--topics, --exclude)")
        unplayed = [t for t in args.wait_for if t not in chosen]
        if unplayed:
            raise InputError(unplayed[0], "--wait-for names a topic that is not replayed (--topics, --exclude)")
        classes = {t: message_class(kind) for t, (kind, _, _) in chosen.items()}
    except InputError as exc:
        print(f"replay: {exc}", file=sys.stderr)
        return 2
    for topic in commands:
        print(f"replay: not replaying {topic}, a motion command: a live arm on this ROS domain would move "
              "(name it in --topics to replay it)", file=sys.stderr, flush=True)

    die_with_parent()
    # From here a Ctrl-C is a KeyboardInterrupt (below), so that the node is destroyed.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    node = None
    code = 0
    initialised = False
    try:
        try:
            try:
                rclpy.init(args=["replay"] + ros_args)
            except ROS_ARGUMENT_ERRORS as exc:
                raise InputError("--ros-args", rcl_error_line(exc)) from None
            initialised = True
            node = rclpy.create_node("replay")
            publishers = {t: node.create_publisher(classes[t], t, qos_of(profiles))
                          for t, (_, _, profiles) in chosen.items()}
            deadline = time.monotonic() + args.wait_timeout
            for topic in args.wait_for:
                # Matched, not only discovered: a reliable volatile message published before the
                # DDS writer and reader match is lost, though the graph already lists the subscriber.
                while publishers[topic].get_subscription_count() == 0:
                    if time.monotonic() > deadline:
                        raise InputError(topic, f"no subscriber after {args.wait_timeout:g} s")
                    rclpy.spin_once(node, timeout_sec=0.05)
            # a segment read alone reports the whole bag's counts per topic: no total then
            total = (f"{sum(count for _, count, _ in chosen.values())} messages" if not lost else
                     f"the messages of {len(parts)} intact segments")
            if not args.quiet:
                print(f"replaying {total} on {len(chosen)} topics from {args.bag} at rate {args.rate:g}", flush=True)
            start_wall = None
            first = None
            sent = 0
            unheard = Counter()  # topic: messages published while no subscriber had matched (lost)
            for topic, _, timestamp, raw in chain.from_iterable(bag.read_messages(part, list(chosen))
                                                                for part in parts):
                if first is None:
                    first, start_wall = timestamp, time.monotonic()
                target = start_wall + (timestamp - first) * 1e-9 / args.rate
                while rclpy.ok():
                    left = target - time.monotonic()
                    if left <= 0:
                        break
                    time.sleep(min(left, 0.05))
                if not rclpy.ok():  # Ctrl-C / SIGTERM
                    break
                publishers[topic].publish(raw)
                sent += 1
                if publishers[topic].get_subscription_count() == 0:
                    unheard[topic] += 1
            for publisher in publishers.values():
                if rclpy.ok() and publisher.qos_profile.reliability == ReliabilityPolicy.RELIABLE:
                    publisher.wait_for_all_acked(Duration(seconds=5))
            if not args.quiet:
                print(f"replayed {sent} messages", flush=True)
            if unheard:  # exit 0 as ros2 bag play, but a replay nothing received is not a silent success
                print(f"replay: warning: {sum(unheard.values())} of {sent} messages went out with no subscriber on "
                      f"their topic ({', '.join(f'{t}: {n}' for t, n in sorted(unheard.items()))}): nothing received "
                      "them; start the listeners first, or give --wait-for", file=sys.stderr, flush=True)
        except (KeyboardInterrupt, ExternalShutdownException):
            code = 0
        except InputError as exc:
            print(f"replay: {exc}", file=sys.stderr)
            code = 2
        except Exception:
            if not initialised or rclpy.ok():
                raise
            # rclpy's C handler shuts the context on a Ctrl-C before the Python one raises: a node or
            # publisher being built on it then fails ('the given context is not valid')
            code = 0
    except KeyboardInterrupt:
        code = 0  # the Ctrl-C's Python handler ran while the error the shut context caused was handled
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C must not break the cleanup
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
