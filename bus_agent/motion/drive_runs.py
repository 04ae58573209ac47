"""The drive-generated motion of one axis: homing (mode 6) and Profile Position / Profile
Velocity runs, a part of :class:`bus_agent.motion.axis.AxisMotion` that steps
:class:`~bus_agent.motion.homing.Homing` and :class:`~bus_agent.motion.profile.ProfileRun`
instead of sampling a ruckig plan. It owns the run under way and the profile parameters last
written; the axis passes what it observed and applies what a step answers (the targets, the
controlword bits, the end of its command). Pure (no clock, no I/O), cycle-safe."""

from __future__ import annotations

from bus_agent.motion.axis_limits import AxisLimits
from bus_agent.motion.config import MotionConfig
from bus_agent.motion.homing import Homing, HomingStep
from bus_agent.motion.planner import Limits
from bus_agent.motion.profile import ProfileRun, ProfileStep, profile_sdo_writes, stop_position

__all__ = ["DriveRuns"]

SdoWrites = tuple[tuple[int, int, bytes], ...]


class DriveRuns:
    """The homing or profile run of an axis configured by ``cfg`` (in counts); ``decel``: the
    axis's acceleration limit, the stop ramp when no profile was written yet."""

    __slots__ = ("_cfg", "_decel", "homing", "profile_run", "_params")

    def __init__(self, cfg: MotionConfig, decel: float) -> None:
        self._cfg = cfg
        self._decel = decel
        #: A homing run under way (mode 6), or None.
        self.homing: Homing | None = None
        #: A Profile Position / Profile Velocity run under way (the drive's own profile), or None.
        self.profile_run: ProfileRun | None = None
        self._params: tuple[int, int, int] | None = None  # 0x6081/0x6083/0x6084 written last

    # ---- homing (mode 6) ---------------------------------------------------------------------

    def start_home(self, method: int, previous_mode: int, now_s: float, deadline_s: float) -> SdoWrites:
        """Start homing with ``method``: the SDO downloads to make first."""
        self.homing = Homing(self._cfg.homing, method, previous_mode, now_s, deadline_s)
        return self.homing.sdo_writes

    def step_homing(self, h: Homing, now_s: float, *, statusword: int, mode: int, enabled: bool, fault: bool,
                    state: str, error_code: int) -> HomingStep:
        """One cycle of homing: ended by a fault or leaving Operation enabled, else by the drive's
        statusword; the run is over when the step has an outcome."""
        if not enabled:
            if fault:
                h.abort("failed", f"drive fault 0x{error_code:04X} in {state} during homing")
            else:
                h.abort("aborted", "quick stop" if state == "quick_stop_active"
                        else f"drive left operation_enabled ({state})")
        hs = h.step(now_s, statusword, mode, enabled)
        if hs.outcome:
            self.homing = None
        return hs

    # ---- SDO answers ---------------------------------------------------------------------------

    def sdo_written(self, error: str) -> tuple[str, bool] | None:
        """The SDO downloads a run asked for finished (``error``: why one was refused). A profile
        run that cannot start answers (its failure, whether it answers its command); else None."""
        if self.homing is not None:
            self.homing.sdo_done(error)
            return None
        r = self.profile_run
        if r is None:
            return None
        failure = r.sdo_done(error)
        if error:
            self._params = None  # unknown now: written again next time
        if not failure:
            return None
        self.profile_run = None
        return failure, r.replies

    # ---- drive-generated profiles (PP move, PV jog) --------------------------------------------

    def start_profile(self, run_kind: str, now_s: float, deadline_s: float, limits: Limits, **kw) -> SdoWrites:
        """Start a ``pp`` or ``pv`` run within ``limits``: the profile SDO downloads to make first
        (none when the drive has these parameters already)."""
        params = (int(round(limits.velocity)), int(round(limits.acceleration)), int(round(limits.acceleration)))
        writes = profile_sdo_writes(*params) if params != self._params else ()
        self._params = params
        self.profile_run = ProfileRun(run_kind, now_s=now_s, deadline_s=deadline_s, sdo_writes=writes,
                                      position_window=self._cfg.position_window,
                                      velocity_window=self._cfg.velocity_window, **kw)
        return writes

    def stop_profile(self, now_s: float, *, enabled: bool, position: int, velocity: int) -> None:
        """After an abort in PP: a stop set-point where the drive comes to rest (0x6084); in PV:
        0x60FF = 0. Neither answers a command."""
        r = self.profile_run
        if r is None or not enabled:
            self.profile_run = None
            return
        if r.kind == "pv":
            r.stop_jog()
            r.replies = False
            return
        decel = float(self._params[2]) if self._params else self._decel
        target = float(round(stop_position(position, velocity, decel)))
        self.profile_run = ProfileRun("pp", target=target, now_s=now_s, deadline_s=now_s + 10.0,
                                      position_window=self._cfg.position_window,
                                      velocity_window=self._cfg.velocity_window, replies=False)

    def step_profile(self, r: ProfileRun, now_s: float, *, statusword: int, position: int, velocity: int,
                     bounds: AxisLimits) -> ProfileStep:
        """One cycle of a profile run (a PV jog stops before a software limit ``bounds`` sees ahead).
        With an outcome the run is over; a PP run that did not arrive is brought to rest on its
        profile."""
        if r.kind == "pv" and r.phase == "running":
            why = bounds.limit_ahead(position, r.velocity)
            if why:
                r.stop_jog(why)
        st = r.step(now_s, statusword, position, velocity)
        if st.outcome:
            self.profile_run = None
            if r.kind == "pp" and r.replies and st.outcome != "done":
                self.profile_run = r  # timeout / following error: bring the drive to rest on its profile
                self.stop_profile(now_s, enabled=True, position=position, velocity=velocity)
        return st

    def abort_homing(self, outcome: str, reason: str) -> bool:
        """End homing with ``outcome`` (bit 4 low, the previous mode restored; its answer comes
        then). False when no homing runs."""
        if self.homing is None:
            return False
        self.homing.abort(outcome, reason)
        return True

    def lose_homing(self) -> int:
        """Forget homing (the drive is lost): the mode to request for its return."""
        h, self.homing = self.homing, None
        assert h is not None
        return h.previous_mode

    def end_profile(self) -> None:
        """Forget the profile run (the drive left Operation enabled, halted, or is lost)."""
        self.profile_run = None
