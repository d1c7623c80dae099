"""The estimator's ~/calibrate action (laser_calib_interfaces/Calibrate): the
long-running calibration, the batch estimate of ~/estimate and then the
diagnosis, beside the service.

Feedback when each stage starts ('estimate', 'diagnosis') and at the end
('done'). A cancel is honoured at once, also within a stage: the core's fits stop
at their next model evaluation (estimation/cancel.py), and the result says how far
the goal got (a goal canceled while another ran computes nothing; one canceled in
the estimate writes no files; one canceled in the diagnosis keeps the estimate's).
Ctrl-C during a stage ends the node without a word to the client (close). Goals
are served one at a time; bad goals are aborted with a one-line message and the
node keeps serving. An estimate that is no calibration (NOT CONVERGED, NOT A
CALIBRATION) is aborted too, its result filled (success false) and its files
written, as the command line exits 3 for it.
"""

from __future__ import annotations

import json
import threading
import traceback
from dataclasses import replace

from rclpy.action import ActionServer, CancelResponse
from rclpy.callback_groups import ReentrantCallbackGroup

from laser_calib.estimation.cancel import Cancelled, cancellable
from laser_calib.io.errors import InputError
from laser_calib.session.estimate import run_calibration, run_diagnosis

from laser_calib_nodes import common, responses
from laser_calib_nodes.sample_rows import request_options, request_sets


class CalibrateServer:
    def __init__(self, node):
        from laser_calib_interfaces.action import Calibrate
        self.node, self.Calibrate = node, Calibrate
        self.busy = threading.Lock()
        # reentrant: cancel requests are taken while a goal executes
        self.server = ActionServer(node, Calibrate, common.PRIVATE_CALIBRATE, self.execute,
                                   cancel_callback=lambda goal: CancelResponse.ACCEPT,
                                   goal_service_qos_profile=common.KEEP_ALL_QOS,
                                   result_service_qos_profile=common.KEEP_ALL_QOS,
                                   cancel_service_qos_profile=common.KEEP_ALL_QOS,
                                   callback_group=ReentrantCallbackGroup())

    def execute(self, goal):
        node, request, result = self.node, goal.request, self.Calibrate.Result()

        def stage(name: str, fraction: float, message: str = "") -> None:
            goal.publish_feedback(self.Calibrate.Feedback(stage=name, fraction_done=fraction, message=message))

        def requested() -> bool:
            return goal.is_cancel_requested

        with self.busy:
            if goal.is_cancel_requested:  # while an earlier goal held the server
                return self._canceled(goal, result, "canceled before the estimate started; nothing was computed")
            outcome = None
            try:
                samples, test, sources = request_sets(node, request)
                output_dir = common.request_output_dir(request.output_dir)
                options = request_options(node, request)
                stage("estimate", 0.0)
                with cancellable(requested):
                    outcome = run_calibration(node.robot, samples, options, output_dir, sources=sources,
                                              compensator=node.compensator, test=test)
                if request.diagnose and goal.is_cancel_requested:
                    return self._canceled(goal, result,
                                          f"canceled before the diagnosis; the estimate: {outcome.message}")
                if request.diagnose:
                    stage("diagnosis", 0.5, outcome.message)
                    with cancellable(requested):
                        diagnosis = run_diagnosis(node.robot, samples, options, output_dir, test, sources)
                    outcome = replace(outcome, diagnosis_json=json.dumps(diagnosis))
            except Cancelled:
                if outcome is None:
                    return self._canceled(goal, result, "canceled during the estimate; no file was written")
                return self._canceled(goal, result,
                                      f"canceled during the diagnosis; the estimate: {outcome.message}")
            except InputError as exc:
                result.message = str(exc)
                node.get_logger().warning(f"calibration refused: {exc}")
                goal.abort()
                return result
            except Exception as exc:  # as ~/estimate: rclpy aborted the goal with an empty message
                result.message = f"internal error: {type(exc).__name__}: {exc}"
                node.get_logger().error(result.message + "\n" + traceback.format_exc())
                goal.abort()
                return result
        responses.fill(result, outcome, node.robot, len(samples), node.get_clock().now().to_msg())
        stage("done", 1.0, outcome.message)
        if outcome.calibration.failure:  # its files are written, but it is no calibration: the goal failed
            goal.abort()
            node.get_logger().error(outcome.message)
        else:
            goal.succeed()
            common.log_warned(node.get_logger(), outcome.warned, outcome.message)
        return result

    def _canceled(self, goal, result, message: str):
        goal.canceled()
        result.message = message
        self.node.get_logger().info(message)
        return result

    def close(self) -> None:
        """The node's cleanup (Ctrl-C) while a goal's stage runs to its end: by then the signal
        has shut the context down, so no client can be told; the server is destroyed before the
        node, so that the stage, once it ends, finds its goal handle gone (rclpy then ignores its
        feedback and state) rather than the node's publishers (an RCLError traceback)."""
        self.server.destroy()
