"""The drive-generated motion of one axis: homing (mode 6) and Profile Position / Profile
Velocity runs, the part of :class:`bus_agent.motion.axis.AxisMotion` that steps
:class:`~bus_agent.motion.homing.Homing` and :class:`~bus_agent.motion.profile.ProfileRun`
instead of sampling a ruckig plan. Pure (no clock, no I/O), cycle-safe."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Mapping

from bus_agent.motion.config import HOMING_METHODS, MotionConfig
from bus_agent.motion.homing import CONTROLWORD_HOMING_START, Homing
from bus_agent.motion.planner import Limits, Plan
from bus_agent.motion.profile import ProfileRun, profile_sdo_writes, stop_position
from bus_agent.motion.records import Active, AxisState, Finished, Rejected
from bus_agent.motion.records import num as _num

__all__ = ["DriveRunsMixin"]

_Active = Active


class DriveRunsMixin:
    """Homing and PP/PV runs of :class:`~bus_agent.motion.axis.AxisMotion` (its state is declared
    here for the type checker and created in ``AxisMotion.__init__``)."""

    if TYPE_CHECKING:
        cfg: MotionConfig
        user: MotionConfig
        scale: float
        limits: Limits
        homed: bool
        active: Active | None
        plan: Plan | None
        homing: Homing | None
        profile_run: ProfileRun | None
        _profile_params: tuple[int, int, int] | None
        sdo_request: tuple[tuple[int, int, bytes], ...] | None
        mode_request: int | None
        controlword_bits: int
        write: bool
        target_position: int
        target_velocity: int
        enabled: bool
        fault: bool
        state: str
        error_code: int
        position: int
        velocity: int
        mode: int
        statusword: int

        @property
        def axis_state(self) -> AxisState: ...

        def check(self, op: str) -> None: ...

        def _limits(self, args: Mapping[str, Any], notes: list[str]) -> Limits: ...

        def prepare_move(self, args: Mapping[str, Any], now_s: float, drive_profile: bool = False) -> Any: ...

        def abort(self, reason: str, now_s: float, *, decelerate: bool = True,
                  outcome: str = "aborted") -> list[Finished]: ...

        def _csv_limit_ahead(self, velocity: float, lim: Limits | None = None) -> str: ...

        def _jog_velocity(self, args: Mapping[str, Any]) -> tuple[float, Limits, list[str]]: ...

    def start_home(self, token: Any, request_id: str, args: Mapping[str, Any], now_s: float, deadline_s: float,
                   previous_mode: int) -> list[Finished]:
        """Start homing in mode 6 (``method``: default the axis's configured one). The cycle then
        writes :attr:`Homing.sdo_writes` by SDO and reports with :meth:`sdo_written`."""
        try:
            self.check("home")
            if self.plan is not None or self.active is not None:
                raise Rejected(f"home needs the axis at standstill (it is in {self.axis_state.value}): "
                               "halt or wait for the running command first")
            method = args.get("method", self.cfg.homing.method)
            if method not in HOMING_METHODS:
                raise Rejected(f"homing method {method!r} is not a supported 0x6098 method "
                               "(1..14, 17..30, 33, 34, 35, 37)")
        except Rejected as e:
            return [Finished(token, request_id, "rejected", str(e))]
        self.homing = Homing(self.cfg.homing, int(method), previous_mode, now_s, deadline_s)
        self.sdo_request = self.homing.sdo_writes
        self.active = _Active(token, request_id, "home", deadline_s)
        return []

    def sdo_written(self, error: str) -> list[Finished]:
        """The SDO downloads of :attr:`sdo_request` finished (``error``: why one was refused)."""
        if self.homing is not None:
            self.homing.sdo_done(error)
            return []
        r = self.profile_run
        if r is None:
            return []
        failure = r.sdo_done(error)
        if error:
            self._profile_params = None  # unknown now: written again next time
        if not failure:
            return []
        self.profile_run = None
        a, self.active = self.active, None
        return [Finished(a.token, a.request_id, "failed", failure)] if a is not None and r.replies else []

    # ---- drive-generated profiles (PP move, PV jog) --------------------------------------------

    def _start_profile(self, token: Any, request_id: str, op: str, run_kind: str, now_s: float, deadline_s: float,
                       limits: Limits, **kw: Any) -> list[Finished]:
        ended = self.abort(f"aborted by {request_id} ({op})", now_s, decelerate=False)
        self.plan = None
        params = (int(round(limits.velocity)), int(round(limits.acceleration)), int(round(limits.acceleration)))
        writes = profile_sdo_writes(*params) if params != self._profile_params else ()
        self._profile_params = params
        self.profile_run = ProfileRun(run_kind, now_s=now_s, deadline_s=deadline_s, sdo_writes=writes,
                                      position_window=self.cfg.position_window,
                                      velocity_window=self.cfg.velocity_window, **kw)
        if writes:
            self.sdo_request = writes
        self.active = _Active(token, request_id, op, deadline_s)
        return ended

    def _pp_move(self, token: Any, request_id: str, args: Mapping[str, Any], now_s: float,
                 deadline_s: float) -> list[Finished]:
        _start, target, limits, notes = self.prepare_move(args, now_s, drive_profile=True)
        return self._start_profile(token, request_id, "move", "pp", now_s, deadline_s, limits,
                                   target=float(round(target)), note="; ".join(notes))

    def _pv_jog(self, token: Any, request_id: str, args: Mapping[str, Any], now_s: float,
                deadline_s: float) -> list[Finished]:
        self.check("jog")
        velocity, lim, notes = self._jog_velocity(args)
        speed = abs(velocity)
        if self._csv_limit_ahead(velocity, lim):
            raise Rejected(f"too close to the software limit {'max' if velocity > 0 else 'min'}_position to jog "
                           "that way: jog the other way")
        stop_s = speed / lim.acceleration
        for_s = _num(args, "for_s")
        end_s = now_s + for_s if for_s is not None else deadline_s - stop_s - 0.05
        if end_s + stop_s > deadline_s + 1e-9:
            raise Rejected(f"jog for {for_s:g} s cannot stop within the command's timeout "
                           f"({deadline_s - now_s:.3g} s; stopping takes {stop_s:.3g} s)")
        return self._start_profile(token, request_id, "jog", "pv", now_s, deadline_s,
                                   Limits(speed, lim.acceleration, lim.jerk), velocity=velocity, end_s=end_s,
                                   note="; ".join(notes))

    def _profile_stop(self, now_s: float) -> None:
        """After an abort in PP: a stop set-point where the drive comes to rest (0x6084); in PV:
        0x60FF = 0. Neither answers a command."""
        r = self.profile_run
        if r is None or not self.enabled:
            self.profile_run = None
            return
        if r.kind == "pv":
            r.stop_jog()
            r.replies = False
            return
        decel = float(self._profile_params[2]) if self._profile_params else self.limits.acceleration
        target = float(round(stop_position(self.position, self.velocity, decel)))
        self.profile_run = ProfileRun("pp", target=target, now_s=now_s, deadline_s=now_s + 10.0,
                                      position_window=self.cfg.position_window,
                                      velocity_window=self.cfg.velocity_window, replies=False)

    def _step_profile(self, r: ProfileRun, now_s: float) -> list[Finished]:
        ended: list[Finished] = []
        if r.kind == "pv" and r.phase == "running":
            why = self._csv_limit_ahead(r.velocity)
            if why:
                r.stop_jog(why)
        st = r.step(now_s, self.statusword, self.position, self.velocity)
        self.write = True
        if r.kind == "pp":
            self.target_position = int(round(r.target))
        else:
            self.target_position = self.position
            self.target_velocity = r.target_velocity
        self.controlword_bits = st.controlword_bits
        if not st.outcome:
            return ended
        self.profile_run = None
        a = self.active
        if a is not None and (r.replies or a.op == "stop"):
            self.active = None
            if a.op == "stop":
                ended.append(Finished(a.token, a.request_id, "done", "at rest; motion refused until released"))
            else:
                ended.append(Finished(a.token, a.request_id, st.outcome, st.reason))
        if r.kind == "pp" and r.replies and st.outcome != "done":
            self.profile_run = r  # timeout / following error: bring the drive to rest on its profile
            self._profile_stop(now_s)
        return ended

    def _step_homing(self, h: Homing, now_s: float) -> list[Finished]:
        if not self.enabled:
            if self.fault:
                h.abort("failed", f"drive fault 0x{self.error_code:04X} in {self.state} during homing")
            else:
                h.abort("aborted", "quick stop" if self.state == "quick_stop_active"
                        else f"drive left operation_enabled ({self.state})")
        hs = h.step(now_s, self.statusword, self.mode, self.enabled)
        # the targets follow the actual values throughout (no jump when the previous mode returns)
        self.write = True
        self.target_position = self.position
        self.target_velocity = 0
        self.controlword_bits = CONTROLWORD_HOMING_START if hs.start_bit else 0
        if hs.request_mode is not None:
            self.mode_request = hs.request_mode
        if not hs.outcome:
            return []
        self.homing = None
        self.homed = h.homed
        a, self.active = self.active, None
        return [Finished(a.token, a.request_id, hs.outcome, hs.reason)] if a is not None else []

