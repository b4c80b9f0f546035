"""What keo puts on the ROS 2 wire besides the payload, checked against pyzeros (an rmw_zenoh
implementation nobody here wrote), and the noise a published covariance stands on."""

from __future__ import annotations

import math

import numpy as np
import pytest
import pyzeros.utils as pyzeros_utils

from keo_service.core.observer import (
    MIN_NOISE_M,
    covariance_noise,
    estimate_variance,
    tracker_noise_floor,
)
from keo_service.live.ros2 import entity_gid


@pytest.mark.parametrize(
    "key",
    [
        "@ros2_lv/0/1a2b3c/0/1/MP/%/%/keo_demo/%keo%demo%kinematic_error/"
        "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/RIHS01_9a3b/::,10:,:,:,,",
        "@ros2_lv/7/ffee/0/2/MP/%/%/keo_c/%tf/tf2_msgs::msg::dds_::TFMessage_/RIHS01_0/::,10:,:,:,,",
        "x",
    ],
)
def test_the_publisher_gid_is_rmw_zenohs(key):
    # rmw_zenoh: gid = XXH3-128 of the exact liveliness key expression, low half first
    assert entity_gid(key) == pyzeros_utils.rmw_zenoh_gid(key)
    assert len(entity_gid(key)) == 16


def test_the_noise_floor_comes_from_the_tracker_uncertainty():
    # "15 um + 6 um/m" at 5 m from the tracker: 45 um per coordinate, 450 urad over 0.1 m
    floor = tracker_noise_floor(15.0, 6.0, [3.0, 0.0, 4.0], 6)
    assert floor == pytest.approx([45e-6] * 3 + [450e-6] * 3, rel=1e-12)
    assert tracker_noise_floor(15.0, 6.0, [3.0, 0.0, 4.0], 3) == pytest.approx([45e-6] * 3)
    # a datasheet of zeros still claims no perfect knowledge
    assert np.all(tracker_noise_floor(0.0, 0.0, None, 6) >= MIN_NOISE_M)


def test_the_published_noise_is_never_zero():
    floor = tracker_noise_floor(15.0, 6.0, [2.0, 0.0, 0.0], 6)
    assert np.array_equal(covariance_noise(None, floor), floor)  # nothing measured yet
    assert np.array_equal(covariance_noise(np.zeros(6), floor), floor)  # noise-free input
    loud = np.full(6, 1e-3)
    assert np.array_equal(covariance_noise(loud, floor), loud)  # measured above the floor
    # the covariance keo publishes from it: (sqrt(a / (2 - a)) s)^2, a = 1 - exp(-L T)
    a = 1.0 - math.exp(-2.0 * 0.01)
    variance = estimate_variance(covariance_noise(None, floor), [2.0] * 6, 0.01)
    assert variance[0] == pytest.approx(a / (2 - a) * 27e-6**2, rel=1e-12)
    assert np.all(variance > 0)
