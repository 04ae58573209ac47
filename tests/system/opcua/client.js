// An independent OPC UA client for the drives-opcua tests (node-opcua-client, not asyncua).
//
// Reads one JSON command per line on stdin and answers each with one JSON line on stdout
// ({"id": N, "ok": true, ...} or {"id": N, "ok": false, "error": "..."}); data changes and
// events of its subscriptions come as {"kind": "data" | "event", ...} lines in between.
// Commands: connect, browse, read, call, subscribe, events, close (see tests/system/opcuabed.py).
"use strict";
const fs = require("fs");
const readline = require("readline");
const {
    OPCUAClient, MessageSecurityMode, SecurityPolicy, AttributeIds, UserTokenType, TimestampsToReturn,
    DataType, Variant, ClientSubscription, ClientMonitoredItem, constructEventFilter,
    coerceNodeId,
} = require("node-opcua-client");
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");

let client = null;
let session = null;
let subscription = null;

function out(obj) { process.stdout.write(JSON.stringify(obj) + "\n"); }

function der(pemFile) {
    const b64 = fs.readFileSync(pemFile, "utf8").replace(/-----[^-]+-----/g, "").replace(/\s+/g, "");
    return Buffer.from(b64, "base64");
}

function plain(v) {
    if (v === null || v === undefined) return null;
    if (typeof v === "bigint") return Number(v);
    if (Array.isArray(v)) return v.map(plain);
    if (v.text !== undefined && v.locale !== undefined) return v.text;  // LocalizedText
    if (v instanceof Uint8Array) return Buffer.from(v).toString("hex");
    if (typeof v === "object" && v.toString && v.constructor && v.constructor.name === "NodeId") return v.toString();
    if (typeof v === "object" && v.high !== undefined && v.low !== undefined && Array.isArray(v) === false) return v;
    return v;
}

async function connect(c) {
    const mode = MessageSecurityMode[c.securityMode || "None"];
    const policy = c.securityMode && c.securityMode !== "None" ? SecurityPolicy.Basic256Sha256 : SecurityPolicy.None;
    // Trust the deployment's CA (the server's certificate is issued by it); without one, any server.
    const manager = new OPCUACertificateManager({ rootFolder: c.pkiFolder,
                                                  automaticallyAcceptUnknownCertificate: !c.caCert });
    await manager.initialize();
    if (c.caCert) {
        await manager.addIssuer(der(c.caCert), false, true);
        await manager.addRevocationList(der(c.caCert.replace(/\.pem$/, ".crl")));
    }
    const options = {
        applicationName: "drives-opcua test client",
        applicationUri: c.applicationUri || "urn:zenoh-drives:test-client",
        endpointMustExist: false,
        securityMode: mode,
        securityPolicy: policy,
        connectionStrategy: { maxRetry: 0, initialDelay: 100, maxDelay: 200 },
        clientCertificateManager: manager,
        requestedSessionTimeout: 60000,
    };
    if (c.transactionTimeout) {
        options.defaultTransactionTimeout = c.transactionTimeout;  // a refusal ends in a timeout (docs/opcua.md)
    }
    if (c.clientCert) {
        options.certificateFile = c.clientCert;
        options.privateKeyFile = c.clientKey;
    }
    client = OPCUAClient.create(options);
    client.on("backoff", () => { throw new Error("connection refused, not retrying"); });
    await client.connect(c.endpoint);
    let identity = { type: UserTokenType.Anonymous };
    if (c.user && c.user.type === "password") {
        identity = { type: UserTokenType.UserName, userName: c.user.name, password: c.user.password };
    } else if (c.user && c.user.type === "certificate") {
        identity = { type: UserTokenType.Certificate, certificateData: der(c.user.cert),
                     privateKey: fs.readFileSync(c.user.key, "utf8") };
    }
    session = await client.createSession(identity);
    const ns = await session.readNamespaceArray();
    return { namespaces: ns };
}

async function browse(c) {
    const res = await session.browse(c.nodeId);
    return { status: res.statusCode.name,
             refs: (res.references || []).map(r => ({ name: r.browseName.name, nodeId: r.nodeId.toString(),
                                                       nodeClass: r.nodeClass })) };
}

async function read(c) {
    const dv = await session.read({ nodeId: c.nodeId, attributeId: AttributeIds.Value });
    return { status: dv.statusCode.name, value: plain(dv.value.value),
             dataType: DataType[dv.value.dataType] };
}

async function call(c) {
    const inputArguments = (c.args || []).map(a => new Variant({ dataType: DataType[a.dataType], value: a.value }));
    const res = await session.call({ objectId: c.objectId, methodId: c.methodId, inputArguments });
    return { status: res.statusCode.name,
             outputs: (res.outputArguments || []).map(v => plain(v.value)),
             inputResults: (res.inputArgumentResults || []).map(s => s.name),
             diagnostics: (res.inputArgumentDiagnosticInfos || []).map(d => d ? d.additionalInfo : null) };
}

async function ensureSubscription() {
    if (!subscription) {
        subscription = ClientSubscription.create(session, {
            requestedPublishingInterval: 50, requestedLifetimeCount: 1000, requestedMaxKeepAliveCount: 20,
            maxNotificationsPerPublish: 1000, publishingEnabled: true, priority: 10,
        });
        await new Promise((resolve, reject) => {
            subscription.on("started", resolve);
            subscription.on("error", reject);
        });
    }
    return subscription;
}

async function subscribe(c) {
    const sub = await ensureSubscription();
    for (const nodeId of c.nodeIds) {
        const item = ClientMonitoredItem.create(sub, { nodeId, attributeId: AttributeIds.Value },
            { samplingInterval: 0, discardOldest: true, queueSize: 100 }, TimestampsToReturn.Both);
        item.on("changed", dv => out({ kind: "data", nodeId, value: plain(dv.value.value), status: dv.statusCode.name,
                                        t: Date.now() }));
    }
    return { monitored: c.nodeIds.length };
}

async function events() {
    const sub = await ensureSubscription();
    const fields = ["Severity", "Message", "SourceName", "SourceNode", "Time"];
    const item = ClientMonitoredItem.create(sub, { nodeId: coerceNodeId("i=2253"), attributeId: AttributeIds.EventNotifier },
        { samplingInterval: 0, discardOldest: true, queueSize: 1000, filter: constructEventFilter(fields) },
        TimestampsToReturn.Both);
    await new Promise((resolve, reject) => {
        item.on("initialized", resolve);
        item.on("err", msg => reject(new Error(`event monitored item refused: ${msg}`)));
    });
    item.on("changed", values => {
        const ev = { kind: "event", t: Date.now() };
        fields.forEach((f, i) => { ev[f] = plain(values[i].value); });
        out(ev);
    });
    return { fields };
}

async function close() {
    if (session) await session.close();
    if (client) await client.disconnect();
    session = null;
    client = null;
    subscription = null;
    return {};
}

const handlers = { connect, browse, read, call, subscribe, events, close };

const rl = readline.createInterface({ input: process.stdin });
let chain = Promise.resolve();
rl.on("line", line => {
    chain = chain.then(async () => {
        const c = JSON.parse(line);
        try {
            const res = await handlers[c.op](c);
            out({ id: c.id, ok: true, ...res });
        } catch (err) {
            out({ id: c.id, ok: false, error: String(err && err.message || err) });
        }
    });
});
rl.on("close", () => { chain.then(close).catch(() => {}).finally(() => process.exit(0)); });
