"""The OPC UA server: an asyncua address space kept current from a :class:`supervisor.fleet.Fleet`.

Data flow: the Fleet (its own threads) calls :meth:`Bridge.on_status` / ``on_agent`` /
``on_host``; they keep the newest message per drive and host and wake the server's asyncio loop
once (``call_soon_threadsafe``), where :meth:`DrivesServer._apply` writes the variables whose
values changed and triggers events. A status reaches the address space within milliseconds of
the Fleet receiving it; at rest (heartbeats with equal values) nothing is written.

Methods run the Fleet's blocking commands on a thread pool, inside ``Fleet.acting_for(user)``,
so every request names the OPC UA user (``on_behalf_of``) and each addressed drive gets the
Fleet's one terminal answer.

Node ids are strings in the ``urn:zenoh-drives`` namespace: ``Drives/<host>`` and
``Drives/<host>/<axis>`` for objects, ``.../<Variable>`` for variables, ``DriveType/<Method>``
for the methods every drive references (one method node per name, shared by all drives: the
call's object id says which drive).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextvars
import logging
import threading
from pathlib import Path
from typing import Any, Sequence

from asyncua import Node, Server, ua

from schemas.messages import AgentStatus, DriveStatus
from supervisor.fleet import Fleet
from supervisor.selectors import DriveRef

from . import model
from .auth import CURRENT_USER, DrivesUser, DrivesUserManager, ServiceRules, guard_channels

log = logging.getLogger("drives_opcua")

#: Threads running Fleet commands (each blocks until its drives answered).
COMMAND_THREADS = 8


class Bridge:
    """Fleet callbacks -> the server's loop: the newest status per drive and host, one wake-up."""

    def __init__(self, loop: asyncio.AbstractEventLoop, wake: asyncio.Event) -> None:
        self.loop = loop
        self.wake = wake
        self.lock = threading.Lock()
        self.drives: dict[DriveRef, DriveStatus] = {}
        self.agents: dict[str, AgentStatus] = {}
        self.hosts: dict[str, bool] = {}
        self.pending = False

    def _poke(self) -> None:
        # Under the lock: one wake-up per batch, however many statuses arrive before it runs.
        if not self.pending:
            self.pending = True
            self.loop.call_soon_threadsafe(self.wake.set)

    def on_status(self, st: DriveStatus) -> None:
        with self.lock:
            self.drives[DriveRef(st.host, st.axis)] = st
            self._poke()

    def on_agent(self, st: AgentStatus) -> None:
        with self.lock:
            self.agents[st.host] = st
            self._poke()

    def on_host(self, host: str, alive: bool) -> None:
        with self.lock:
            self.hosts[host] = alive
            self._poke()

    def take(self) -> tuple[dict[DriveRef, DriveStatus], dict[str, AgentStatus], dict[str, bool]]:
        with self.lock:
            out = (self.drives, self.agents, self.hosts)
            self.drives, self.agents, self.hosts = {}, {}, {}
            self.pending = False
            return out


class DrivesServer:
    """``drives-opcua``: the address space, its updates from the Fleet, and the drive methods."""

    def __init__(self, fleet: Fleet, endpoint: str, *, pki: str | Path | None = None, identity: str | None = None,
                 accept_unknown_clients: bool = False) -> None:
        self.fleet = fleet
        self.endpoint = endpoint
        self.pki = None if pki is None else Path(pki)
        self.identity = identity
        self.accept_unknown_clients = accept_unknown_clients
        self.users = DrivesUserManager(self.pki)
        self.server = Server(user_manager=self.users)
        self.users.install(self.server.iserver)
        self.idx = 0
        self.drives_folder: Node | None = None
        self.host_nodes: dict[str, Node] = {}
        self.drive_nodes: dict[DriveRef, Node] = {}
        self.by_nodeid: dict[ua.NodeId, DriveRef] = {}
        self.method_nodes: list[Node] = []
        self.drive_shown: dict[DriveRef, tuple[Any, ...]] = {}
        self.drive_last: dict[DriveRef, DriveStatus] = {}
        self.host_shown: dict[str, tuple[Any, ...]] = {}
        self.host_view: dict[str, model.HostView] = {}
        self.events: Any = None
        self.pool = concurrent.futures.ThreadPoolExecutor(COMMAND_THREADS, thread_name_prefix="opcua-cmd")
        self.wake = asyncio.Event()
        self.bridge: Bridge | None = None
        self.writes = 0  # variable writes done (benchmarks)

    # ---- set-up ---------------------------------------------------------------------------

    async def init(self) -> None:
        s = self.server
        await s.init()
        s.set_endpoint(self.endpoint)
        s.set_server_name("zenoh-drives OPC UA")
        policies = [ua.SecurityPolicyType.NoSecurity]
        tokens: list[type] = [ua.AnonymousIdentityToken]
        if self.pki is not None and self.identity is not None:
            from bus_agent.security.pki import opcua_uri
            files = server_files(self.pki, self.identity)
            await s.load_certificate(str(files.cert), format="pem")
            await s.load_private_key(str(files.key), format="pem")
            await s.set_application_uri(opcua_uri(self.identity))
            policies.append(ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt)
            tokens += [ua.UserNameIdentityToken, ua.X509IdentityToken]
        s.set_security_policy(policies, permission_ruleset=ServiceRules())
        s.set_identity_tokens(tokens)
        self.idx = await s.register_namespace(model.NAMESPACE_URI)
        self.drives_folder = await s.nodes.objects.add_folder(self._nid(model.ROOT_FOLDER), model.ROOT_FOLDER)
        await self._add_methods()
        self.events = await s.get_event_generator()

    def _nid(self, path: str) -> ua.NodeId:
        return ua.NodeId(path, self.idx)

    async def _add_methods(self) -> None:
        dtype = await self.server.nodes.base_object_type.add_object_type(self._nid("DriveType"), "DriveType")
        outputs = [ua.Argument(Name=n, DataType=ua.NodeId(ua.ObjectIds.String), ValueRank=-1,
                               Description=ua.LocalizedText(d)) for n, d in model.OUTPUTS]
        for name, spec in model.METHODS.items():
            inputs = [ua.Argument(Name=a.name, DataType=ua.NodeId(ua.ObjectIds.Double), ValueRank=-1,
                                  Description=ua.LocalizedText(a.description)) for a in spec.arguments]
            node = await dtype.add_method(self._nid(f"DriveType/{name}"), name, self._handler(name, spec),
                                          inputs, outputs)
            await node.write_attribute(ua.AttributeIds.Description, ua.DataValue(ua.LocalizedText(spec.description)))
            self.method_nodes.append(node)

    async def _host_node(self, host: str) -> Node:
        node = self.host_nodes.get(host)
        if node is None:
            assert self.drives_folder is not None
            node = await self.drives_folder.add_object(self._nid(f"{model.ROOT_FOLDER}/{host}"), host)
            view = model.HostView(False, None)
            for (name, (vtype, _)), value in zip(model.HOST_VARIABLES.items(), model.host_values(view)):
                await node.add_variable(self._nid(f"{model.ROOT_FOLDER}/{host}/{name}"), name, value, vtype)
            self.host_nodes[host] = node
            self.host_view[host] = view
            self.host_shown[host] = model.host_values(view)
        return node

    async def _drive_node(self, ref: DriveRef) -> Node:
        node = self.drive_nodes.get(ref)
        if node is None:
            host = await self._host_node(ref.host)
            base = f"{model.ROOT_FOLDER}/{ref.host}/{ref.axis}"
            node = await host.add_object(self._nid(base), ref.axis)
            for name, (vtype, _) in model.DRIVE_VARIABLES.items():
                var = await node.add_variable(self._nid(f"{base}/{name}"), name, model.DRIVE_INITIAL[name], vtype)
                # Until the first status: no value yet (an expected drive whose agent is offline).
                await self.server.write_attribute_value(var.nodeid, ua.DataValue(
                    ua.Variant(model.DRIVE_INITIAL[name], vtype),
                    StatusCode=ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData)))
            for m in self.method_nodes:
                await node.add_reference(m.nodeid, ua.ObjectIds.HasComponent, forward=True, bidirectional=False)
            self.drive_nodes[ref] = node
            self.by_nodeid[node.nodeid] = ref
        return node

    async def populate(self) -> None:
        """Expected hosts and drives (``--fleet``) and what the Fleet already knows."""
        for ref in self.fleet.expected_drives():
            await self._drive_node(ref)
        if self.fleet.expected is not None:
            for host in self.fleet.expected.hosts:
                await self._host_node(host)
        loop = asyncio.get_running_loop()
        self.bridge = bridge = Bridge(loop, self.wake)
        self.fleet.on("status", bridge.on_status)
        self.fleet.on("agent", bridge.on_agent)
        self.fleet.on("arrival", lambda h: bridge.on_host(h, True))
        self.fleet.on("departure", lambda h: bridge.on_host(h, False))
        # What the Fleet saw before the listeners were there.
        for host, info in self.fleet.agents().items():
            bridge.on_host(host, info.alive)
            if info.status is not None:
                bridge.on_agent(info.status)
        for st in self.fleet.drives().values():
            bridge.on_status(st)

    # ---- updates --------------------------------------------------------------------------

    async def run_updates(self) -> None:
        """Apply what the Fleet brought, each time it wakes us; forever."""
        assert self.bridge is not None
        while True:
            await self.wake.wait()
            self.wake.clear()
            drives, agents, hosts = self.bridge.take()
            try:
                await self._apply(drives, agents, hosts)
            except Exception:
                log.exception("opcua: applying fleet updates failed")

    async def _apply(self, drives: dict[DriveRef, DriveStatus], agents: dict[str, AgentStatus],
                     hosts: dict[str, bool]) -> None:
        for n, (ref, st) in enumerate(drives.items()):
            if n % 64 == 63:
                await asyncio.sleep(0)  # a large batch (a fleet arriving) leaves room for the clients
            await self._drive_node(ref)
            values = model.drive_values(st)
            old_values = self.drive_shown.get(ref)
            if values != old_values:
                base = f"{model.ROOT_FOLDER}/{ref.host}/{ref.axis}"
                for i, (name, (vtype, _)) in enumerate(model.DRIVE_VARIABLES.items()):
                    if old_values is None or values[i] != old_values[i]:
                        await self.server.write_attribute_value(self._nid(f"{base}/{name}"),
                                                                ua.DataValue(ua.Variant(values[i], vtype)))
                        self.writes += 1
                self.drive_shown[ref] = values
            for kind, severity, message in model.drive_alarms(self.drive_last.get(ref), st):
                await self._event(self.drive_nodes[ref], f"{ref.host}/{ref.axis}", severity, message)
                log.warning("opcua: event %s (%d): %s", kind, severity, message)
            self.drive_last[ref] = st
        for host in {*agents, *hosts}:
            await self._host_node(host)
            view = self.host_view[host]
            alive = hosts.get(host, view.alive)
            new = model.HostView(alive, agents.get(host, view.status))
            if view.alive != alive:
                kind = "host_online" if alive else "host_offline"
                await self._event(self.host_nodes[host], host, model.SEVERITY[kind],
                                  f"agent {host} {'is online' if alive else 'is offline'}")
            self.host_view[host] = new
            values = model.host_values(new)
            old_values = self.host_shown[host]
            for i, (name, (vtype, _)) in enumerate(model.HOST_VARIABLES.items()):
                if values[i] != old_values[i]:
                    await self.server.write_attribute_value(self._nid(f"{model.ROOT_FOLDER}/{host}/{name}"),
                                                            ua.DataValue(ua.Variant(values[i], vtype)))
                    self.writes += 1
            self.host_shown[host] = values

    async def _event(self, source: Node, name: str, severity: int, message: str) -> None:
        ev = self.events.event
        ev.Severity = severity
        ev.SourceNode = source.nodeid
        ev.SourceName = name
        await self.events.trigger(message=message)

    # ---- methods --------------------------------------------------------------------------

    def _handler(self, name: str, spec: model.Method):
        async def call(parent: ua.NodeId, *args: ua.Variant) -> ua.CallMethodResult:
            return await self._call(name, spec, parent, args)
        return call

    async def _call(self, name: str, spec: model.Method, parent: ua.NodeId,
                    args: Sequence[ua.Variant]) -> ua.CallMethodResult:
        user = CURRENT_USER.get()
        ref = self.by_nodeid.get(parent)
        if ref is None:
            return _answer(ua.StatusCodes.BadMethodInvalid, "rejected", f"{name}: call it on a drive object")
        where = f"{name} on {ref.host}/{ref.axis}"
        if not isinstance(user, DrivesUser) or not user.name:
            return _denied(f"{where}: log in to call methods")
        if not model.may_call(user.roles, spec.op):
            return _denied(f"{where}: {user.name} ({', '.join(user.roles)}) may not {spec.op}; "
                           f"roles that may: {', '.join(model.roles_for(spec.op))}")
        if user.hosts and ref.host not in user.hosts:
            return _denied(f"{where}: {user.name} commands only {', '.join(user.hosts)}")
        try:
            values = model.check_arguments(spec, args)
        except model.ArgumentProblem as exc:
            log.warning("opcua: %s by %s refused: %s", where, user.name, exc)
            res = _answer(exc.status, "rejected", f"{where}: {exc} (nothing sent)")
            res.InputArgumentResults = [ua.StatusCode(exc.status if i == exc.index else ua.StatusCodes.Good)
                                        for i in range(len(args))]
            res.InputArgumentDiagnosticInfos = [ua.DiagnosticInfo(AdditionalInfo=str(exc) if i == exc.index else None)
                                                for i in range(len(args))]
            return res
        log.info("opcua: %s by %s (%s)", where, user.name, user.via)
        ctx = contextvars.copy_context()
        try:
            result = await asyncio.get_running_loop().run_in_executor(
                self.pool, ctx.run, self._send, user.name, spec, str(ref), values)
        except Exception as exc:  # the Fleet refused to send (a selector, a payload): say why
            log.exception("opcua: %s by %s failed", where, user.name)
            return _answer(ua.StatusCodes.BadInternalError, "rejected", f"{where}: not sent: {exc}")
        out, error = model.outcome(result, ref.host, ref.axis)
        log.info("opcua: %s by %s: %s %s", where, user.name, out, error)
        return _answer(ua.StatusCodes.Good, out, error)

    def _send(self, user: str, spec: model.Method, target: str, values: list[float]) -> Any:
        """One Fleet command (or the two-phase enable) for one drive, as ``user`` (blocking: on
        the command pool)."""
        f = self.fleet
        with f.acting_for(user):
            if spec.two_phase:
                return f.enable(target, timeout_s=spec.timeout_s)
            return f.command(spec.op, target, spec.command_args(values), timeout_s=spec.timeout_s)

    # ---- run ------------------------------------------------------------------------------

    async def serve(self, ready: Any = None) -> None:
        """Serve until cancelled; ``ready()`` is called once the endpoint listens."""
        await self.init()
        await self.populate()
        assert self.bridge is not None
        await self._apply(*self.bridge.take())  # what the Fleet knows now, before clients come
        async with self.server:
            if self.pki is not None and not self.accept_unknown_clients:
                from cryptography import x509

                # The policy factories exist once the server started (asyncua builds them then).
                ca = x509.load_pem_x509_certificate((self.pki / "ca.pem").read_bytes())
                assert guard_channels(self.server._policies, ca) >= 1
            updates = asyncio.create_task(self.run_updates())
            if ready is not None:
                ready()
            try:
                await asyncio.Event().wait()
            finally:
                updates.cancel()
                self.pool.shutdown(wait=False, cancel_futures=True)


def server_files(pki: str | Path, identity: str) -> Any:
    """The server's certificate files (``bus_agent.security.pki.Paths``), checked: present, in
    date, its own, and RSA (Basic256Sha256 has no ECDSA). Raises ``PkiError`` saying how to fix it."""
    from cryptography import x509
    from cryptography.hazmat.primitives.asymmetric import rsa

    from bus_agent.security.pki import PkiError, check_identity

    files = check_identity(pki, identity)
    if not isinstance(x509.load_pem_x509_certificate(files.cert.read_bytes()).public_key(), rsa.RSAPublicKey):
        raise PkiError(f"{files.cert}: OPC UA (Basic256Sha256) needs an RSA certificate: issue it with "
                       f"`drives-pki issue {pki} {identity} --role operator --role maintenance --opcua` "
                       "(add --replace to renew an existing one)")
    return files


def _denied(text: str) -> ua.CallMethodResult:
    """A call refused for its user (logged: the server's side of the audit)."""
    log.warning("opcua: denied: %s", text)
    return _answer(ua.StatusCodes.BadUserAccessDenied, "denied", text)


def _answer(status: int, outcome: str, error: str) -> ua.CallMethodResult:
    """A method's result: its status and the two outputs (outcome, error text)."""
    return ua.CallMethodResult(StatusCode=ua.StatusCode(status),
                               OutputArguments=[ua.Variant(outcome, ua.VariantType.String),
                                                ua.Variant(error, ua.VariantType.String)])
