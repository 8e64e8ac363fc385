"""bench.planted: which preset fields each planted error switches off, and its report (no run)."""

from bench.planted import ERRORS, preset_overrides, report


def test_each_error_switches_only_its_own_fields_off():
    from blockloc.sim.presets import get_preset

    base = get_preset("small")
    p = get_preset("small", **preset_overrides("small", ERRORS["imu_time_offset"][1]))
    assert p.imu.time_offset_s == 0.0 < base.imu.time_offset_s
    assert p.imu.scale_factor_sigma == base.imu.scale_factor_sigma and p.lidar == base.lidar
    p = get_preset("small", **preset_overrides("small", ERRORS["mounting"][1]))
    assert p.extrinsic_error_m == p.extrinsic_error_deg == 0.0 and p.imu == base.imu
    p = get_preset("small", **preset_overrides("small", ERRORS["laser_offsets"][1]))
    assert p.lidar.laser_range_offset_m == p.lidar.laser_angle_offset_deg == 0.0
    assert p.lidar.range_noise_m == base.lidar.range_noise_m and p.extrinsic_error_m == base.extrinsic_error_m


def test_the_report_gives_each_errors_gain_against_every_error_on():
    def m(ate):
        return {"ate_trans_rmse_m": ate, "ate_rot_rmse_deg": 0.1, "err_along_mean_m": -0.01, "failures": 0}

    text = report({"none": {"default": m(0.023), "full": {**m(0.030), "translation_estimated": "xy"}},
                   "mounting": {"default": {**m(0.020), "translation_estimated": ""}, "full": m(0.021)}},
                  ["--seed", "2"], "now", 1.0, 2, 400, ["default", "full"], 3.0)
    assert "`python -m bench.planted --seed 2`" in text and "the first 400 frames" in text
    assert "| mounting | LiDAR mounting" in text
    assert "| 0.0200 | +3.0 | 0.100 | -1.0 | 0.0210 | +9.0 |" in text
    # which body axes of the mounting translation each map took from its estimate
    assert "| 0, 0 | -, xy |" in text and "| 0, 0 | nominal, - |" in text
