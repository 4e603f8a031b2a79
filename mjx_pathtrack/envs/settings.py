"""Settings of the path-tracking environment (:class:`EnvConfig`: episode, observation,
termination, end of the path, reward weights) and the named choices they take; the environment
is :class:`mjx_pathtrack.envs.tracking.PathTrackingEnv`."""

from __future__ import annotations

import dataclasses

import numpy as np

from mjx_pathtrack.core import reward as R


#: [rad] deviation shown as 1 in the observation's deviation block (``observe_deviation``): the
#: papers' termination distance
DEVIATION_SCALE = 0.25
#: path-speed ratio shown as 1 in the observation's speed-limit block (``observe_speed_limits``):
#: twice the fastest speed a segment ahead allows
SPEED_RATIO_SCALE = 2.0
#: how the observation shows the next knots (:class:`EnvConfig` ``knots_frame``)
KNOTS_FRAMES = ("absolute", "relative")
#: when braking at the end of the path starts (:class:`EnvConfig` ``end_braking``)
END_BRAKING = ("at_end", "predictive")
#: how the robot stops at the end of the path (:class:`EnvConfig` ``end_stop``)
END_STOP = ("fastest", "end_knot")


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """Episode, observation and termination settings (defaults: papers' iiwa random-path net).

    dt [s]: decision step; n_next: knots ahead in the observation (N); substeps: setpoints per
    step (24 = 1/240 s at dt 0.1); deviation_samples: comparison points per step;
    duration [s]: time budget for a whole path (scaled by the episode's share of it);
    start_range, min_fraction, max_fraction: random sub-path selection (docs/method.md §5);
    terminate_deviation [rad] (None: off); brake_at_end / terminate_on_stop: braking at the end
    and termination once |v|, |a| < stop_velocity / stop_acceleration; success_deviation [rad]:
    final deviation of a successful episode; deviation_weights: per path joint (None: plain L2);
    adjustable: each environment carries its own copy of its path so that the reference ahead
    can be replaced during the episode (:meth:`PathTrackingEnv.replace_reference`); off for
    training, where the state only holds the dataset index (much less memory per environment).
    end_tolerance [rad]: the end counts as reached (braking starts) once the reference position
    is within this arc length of the path end; 0 (the papers): only at the end itself. A
    deterministic policy can stall just short of the end (docs/results.md "Findings of earlier recipes").
    end_braking: when braking towards the end starts: ``"at_end"`` (the papers): once the
    reference position reaches the end (``end_tolerance`` before it); ``"predictive"``: as soon
    as the fastest stop from the current state would carry the robot to the end, i.e. the
    remaining arc length is at most the length of that stop (:meth:`PathTrackingEnv.stop_length`,
    predicted without position limits). A policy that arrives at speed then stops at the end
    instead of overshooting it by its braking distance; braking itself is the same.
    end_stop: how the robot stops once braking at the end started: ``"fastest"`` (the papers):
    every joint brakes on its own as fast as its limits allow, so the joints come to rest at
    different times and the robot ends beside the path; ``"end_knot"``: every path joint comes
    to rest at its coordinate of the end knot (:meth:`PathTrackingEnv.end_knot_acceleration`),
    as fast as the limits allow; the safe range still bounds every acceleration.
    end_knot_tolerance [rad]: with ``end_stop="end_knot"``, a joint whose fastest stop ends this
    close to its end-knot coordinate brakes instead of approaching further: a smaller value ends
    closer to the end knot and takes longer (measured in docs/results.md "The final deviation").
    knots_frame: ``"absolute"`` (the papers' observation: knot positions normalised by the joint
    ranges) or ``"relative"`` (knot minus current position, divided by ``n_next *
    max_dis_between_knots``): same size, but the policy need not learn the subtraction (docs/results.md
    "Findings of earlier recipes" measures the difference).
    observe_deviation: append the deviation vector (reference point at the current arc position
    minus the path joints' position, divided by ``DEVIATION_SCALE`` [rad], clipped) to the
    observation: the offset from the path that the knot blocks show only at 1/(N max_dis) scale
    (tracking task only).
    observe_speed_limits: append, for each of the ``n_next`` knot segments ahead, the robot's
    path-joint speed over the fastest speed that the velocity limits allow along the segment and
    the acceleration limits allow on the turn that ends it (:func:`segment_speed_ratios`), mapped
    from [0, 2] to [-1, 1]: above 0 the robot is faster than that stretch allows and must slow
    down before it. Whatever the curve's shape, the joint that binds on a stretch shows up here
    (tracking task only).
    train_terminate_deviation [rad] (None: ``terminate_deviation``): the deviation at which the
    episodes of the *training* environments end (:func:`mjx_pathtrack.envs.registry.make`,
    split ``"train"``); evaluation, the training's evaluations and reports keep
    ``terminate_deviation``, the bar. A tighter tube in training than the bar leaves the policy a
    margin on paths unlike its training paths (docs/results.md "A tighter tube in training").
    """

    dt: float = 0.1
    n_next: int = 8
    substeps: int = 24
    deviation_samples: int = 16
    duration: float = 16.0
    start_range: tuple[float, float] = (0.0, 0.8)
    min_fraction: float = 0.2
    max_fraction: float = 1.0
    terminate_deviation: float | None = 0.25
    brake_at_end: bool = True
    terminate_on_stop: bool = True
    stop_velocity: float = 0.01
    stop_acceleration: float = 0.01
    success_deviation: float = 0.05
    deviation_weights: tuple[float, ...] | None = None
    reward: R.RewardWeights = R.RewardWeights()
    adjustable: bool = False
    knots_frame: str = "absolute"
    end_tolerance: float = 0.0
    end_braking: str = "at_end"
    end_stop: str = "fastest"
    end_knot_tolerance: float = 0.05
    observe_deviation: bool = False
    observe_speed_limits: bool = False
    train_terminate_deviation: float | None = None

    def __post_init__(self):
        if self.end_braking not in END_BRAKING:
            raise ValueError(f"unknown end_braking {self.end_braking!r}; known: {', '.join(END_BRAKING)}")
        if self.end_stop not in END_STOP:
            raise ValueError(f"unknown end_stop {self.end_stop!r}; known: {', '.join(END_STOP)}")
        if not (np.isfinite(self.end_knot_tolerance) and self.end_knot_tolerance > 0.0):
            raise ValueError(f"end_knot_tolerance must be a finite number > 0 [rad], got {self.end_knot_tolerance}")
        if self.knots_frame not in KNOTS_FRAMES:
            raise ValueError(f"unknown knots_frame {self.knots_frame!r}; known: {', '.join(KNOTS_FRAMES)}")
        if not (np.isfinite(self.end_tolerance) and self.end_tolerance >= 0.0):
            raise ValueError(f"end_tolerance must be a finite number >= 0 [rad], got {self.end_tolerance}")

    def max_episode_steps(self) -> int:
        """Upper bound of the steps of any episode (the whole path at full duration)."""
        return int(round(self.duration / self.dt)) + 1
