"""The physical models behave as docs/models.md says they do."""

import numpy as np
import pytest

from devices.models import catalyst, quantum_dots, spectra, thermal


def grid_peaks():
    out = []
    for c in np.linspace(1, 50, 40):
        for t_c in np.linspace(220, 320, 21):
            for t_s in np.linspace(10, 600, 60):
                out.append(quantum_dots.emission(c, t_c + 273.15, t_s)["peak_nm"])
    return np.array(out)


def test_all_three_colours_are_reachable_inside_the_parameter_box():
    peaks = grid_peaks()
    for target in (630, 520, 450):
        assert np.any(np.abs(peaks - target) <= 5), f"{target} nm is out of reach"


def test_absorption_inverts_yu_sizing_curve():
    def yu_diameter_nm(lam):  # Yu, Qu, Guo, Peng, Chem. Mater. 2003, 15, 2854, CdSe
        return 1.6122e-9 * lam**4 - 2.6575e-6 * lam**3 + 1.6242e-3 * lam**2 - 0.4277 * lam + 41.57

    for lam in (460.0, 520.0, 580.0, 640.0):
        assert quantum_dots.absorption_peak_nm(yu_diameter_nm(lam)) == pytest.approx(lam, abs=0.5)
    assert quantum_dots.emission(20, 560, 200)["peak_nm"] == pytest.approx(
        quantum_dots.absorption_peak_nm(quantum_dots.diameter_nm(20, 560, 200)) + quantum_dots.STOKES_NM)


def test_dots_grow_with_time_temperature_and_concentration():
    d = quantum_dots.diameter_nm
    assert d(20, 540, 30) < d(20, 540, 300)
    assert d(20, 520, 100) < d(20, 580, 100)
    assert d(5, 560, 600) < d(40, 560, 600)


def test_line_width_widens_with_the_size_distribution():
    narrow = quantum_dots.emission(30, 560, 600)
    broad = quantum_dots.emission(30, 560, 20)  # early: before size focusing
    assert broad["sigma_rel"] > narrow["sigma_rel"]
    assert broad["fwhm_nm"] > narrow["fwhm_nm"] >= quantum_dots.HOMOGENEOUS_FWHM_NM


def test_catalyst_yield_peaks_near_450_k_and_selectivity_falls_above_500_k():
    temps = np.arange(380.0, 560.0, 1.0)
    y = [catalyst.run(np.full(720, t), 5.0)["yield"] for t in temps]
    assert abs(temps[int(np.argmax(y))] - 450) <= 3
    sel = catalyst.selectivity(np.array([450.0, 470.0, 500.0, 520.0]))
    assert sel[0] > 0.98 and sel[1] > 0.97
    assert sel[2] < 0.8 and sel[3] < 0.65


def test_pid_holds_the_setpoint_without_windup_overshoot():
    trace = thermal.simulate(450.0, 3600.0)
    settled = trace[len(trace) // 2 :]
    assert np.max(np.abs(settled - 450.0)) < 0.5
    assert np.max(trace) - 450.0 < 3.0


def test_without_anti_windup_the_same_loop_overshoots_more():
    class Naive(thermal.Pid):
        def step(self, error, dt):
            self.integral += error * dt
            u = self.kp * error + self.ki * self.integral
            return min(max(u, 0.0), thermal.U_MAX_K)

    assert np.max(thermal.simulate(450.0, 3600.0, controller=Naive())) > np.max(thermal.simulate(450.0, 3600.0)) + 5


def test_the_peak_fit_recovers_a_noisy_band():
    rng = np.random.default_rng(0)
    y = spectra.render([(523.0, 30.0, 0.8)], 0.01, rng)
    fit = spectra.fit_peak(y)
    assert fit["center"] == pytest.approx(523.0, abs=0.5)
    assert fit["fwhm"] == pytest.approx(30.0, rel=0.05)
    assert fit["height"] == pytest.approx(0.8, rel=0.05)


def test_the_peak_fit_is_numpys_weighted_least_squares_parabola():
    """The closed form ``fit_peak`` solves is ``np.polyfit(x, log y, 2, w=y)``: on bands narrow and wide, faint and
    strong, at the grid's edges too."""
    rng = np.random.default_rng(3)
    fitted = 0
    for _ in range(400):
        y = spectra.render([(rng.uniform(380, 770), rng.uniform(4, 120), rng.uniform(0.01, 1))], rng.uniform(5e-4, 0.1),
                           rng)
        top = int(np.argmax(y))
        near = y > 0.3 * y[top]
        lo = hi = top
        while lo > 0 and near[lo - 1]:
            lo -= 1
        while hi < len(y) - 1 and near[hi + 1]:
            hi += 1
        if hi - lo < 2:
            continue
        x, yy = spectra.GRID_NM[lo:hi + 1] - spectra.GRID_NM[top], y[lo:hi + 1]
        assert spectra._log_parabola(x.tolist(), yy.tolist()) == pytest.approx(np.polyfit(x, np.log(yy), 2, w=yy),
                                                                              rel=1e-9)
        fitted += 1
    assert fitted > 300


def test_ingan_band_gap_bows_between_gan_and_inn():
    from devices.models import bandgap

    assert bandgap.band_gap_ev(0.0) == pytest.approx(3.42)
    assert bandgap.band_gap_ev(1.0) == pytest.approx(0.77)
    assert bandgap.band_gap_ev(0.5) < (3.42 + 0.77) / 2  # bowing pulls the middle down
    assert bandgap.incorporated(0.3, 650) > bandgap.incorporated(0.3, 800) > bandgap.incorporated(0.3, 900)


def test_the_spectrometer_reads_a_band_gap_off_the_absorption_edge():

    from devices.spectrometer import Spectrometer
    from twin.core.clock import LabClock
    from twin.device.driver import DriverSetup, StepContext
    from twin.scenario import Chemistry, Duration

    clock = LabClock("virtual")
    spec = Spectrometer(DriverSetup("s", "spectrometer", {}, Chemistry(model="bandgap", noise=0.005), Duration(mean_s=1), 0))

    async def measure(gap):
        ctx = StepContext(clock, np.random.default_rng(1), Duration(mean_s=1, cv=0), lambda *a: None, lambda r: None)
        return (await spec.run("measure", {}, {"kind": "film", "band_gap_ev": gap, "t_made": 0.0}, ctx)).outputs

    for gap in (2.6, 3.0, 3.3):
        assert clock.run(measure(gap))["band_gap_ev"] == pytest.approx(gap, abs=0.01)


def test_the_peak_fit_on_noise_alone_stays_bounded():
    rng = np.random.default_rng(1)
    for _ in range(2000):
        y = rng.normal(0.0, 0.005, spectra.GRID_NM.shape)
        fit = spectra.fit_peak(y, 610, 670)
        assert 0.0 <= fit["height"] <= float(np.max(y)) * 1.5
