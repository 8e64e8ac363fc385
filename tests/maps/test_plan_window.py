"""plan_keyframes interpolates over the poses around its frames only: the same poses as over
the whole trajectory, for a slice at the start, in the middle and at the end."""

import numpy as np
import pytest


@pytest.mark.parametrize("start, stop", [(0, 120), (151, 307), (500, None)])
def test_planned_poses_are_those_interpolated_over_the_whole_trajectory(start, stop):
    from blockloc.maps.mapping import plan_keyframes
    from blockloc.sim.stream import open_sim_sequence

    seq = open_sim_sequence("tiny", "map", 1)
    plan = plan_keyframes(seq, keyframe_distance_m=0.3, keyframe_angle_deg=10.0, start=start, stop=stop)
    traj = seq.mapping_poses()
    assert len(plan.frames) > 3 and len(traj) > 20 * (len(plan.frames))
    whole = traj.interpolate(plan.stamps) @ np.asarray(seq.info.T_body_lidar, np.float64)
    assert plan.T_map_lidar.tobytes() == whole.tobytes()
