// A second, independent OPC UA client stack (node-opcua) against the daemon's OPC UA server.
// Usage: node client.mjs URL LOOP OPERATOR_PASSWORD VIEWER_PASSWORD PKI_DIR
// Prints one JSON object with what it saw; tests/test_opcua_node.py asserts on it.
import { OPCUACertificateManager } from "node-opcua-certificate-manager";
import {
    AttributeIds, DataType, MessageSecurityMode, OPCUAClient, SecurityPolicy, TimestampsToReturn, UserTokenType,
} from "node-opcua-client";

const [url, loop, operatorPassword, viewerPassword, pki] = process.argv.slice(2);
const NAMESPACE = "urn:relaytune:autotuner";
const out = {};
const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

function client(securityMode, securityPolicy) {
    const clientCertificateManager = new OPCUACertificateManager({
        rootFolder: pki, automaticallyAcceptUnknownCertificate: true,
    });
    return OPCUAClient.create({
        applicationName: "relaytune-node-test", applicationUri: "urn:relaytune:node-test",
        endpointMustExist: false, securityMode, securityPolicy, clientCertificateManager,
        connectionStrategy: { maxRetry: 1, initialDelay: 100, maxDelay: 500 },
    });
}

async function session(c, user, password) {
    await c.connect(url);
    return user === null ? c.createSession() : c.createSession({ type: UserTokenType.UserName, userName: user, password });
}

const text = (err) => String(err && err.message ? err.message : err);
const args = (controller, amp, apply) => [
    { dataType: DataType.String, value: controller }, { dataType: DataType.Double, value: amp },
    { dataType: DataType.Double, value: NaN }, { dataType: DataType.Double, value: NaN },
    { dataType: DataType.Double, value: NaN }, { dataType: DataType.String, value: apply },
];

async function main() {
    // 1. anonymous: refused
    const anon = client(MessageSecurityMode.None, SecurityPolicy.None);
    try {
        await session(anon, null, null);
        out.anonymous = "accepted";
    } catch (err) {
        out.anonymous = text(err);
    } finally {
        await anon.disconnect();
    }

    // 2. viewer on the None endpoint (its password is encrypted with the server's certificate)
    const v = client(MessageSecurityMode.None, SecurityPolicy.None);
    const vs = await session(v, "viewer", viewerPassword);
    const ns = (await vs.readNamespaceArray()).indexOf(NAMESPACE);
    out.ns = ns;
    const browsed = await vs.browse(`ns=${ns};s=Loops`);
    out.loops = browsed.references.map((r) => r.browseName.name);
    const children = await vs.browse(`ns=${ns};s=${loop}`);
    out.children = children.references.map((r) => r.browseName.name);
    out.viewer_tbsy = (await vs.read({ nodeId: `ns=${ns};s=${loop}.TBSY`, attributeIds: AttributeIds.Value })).value.value;
    try {
        const r = await vs.call({ objectId: `ns=${ns};s=${loop}`, methodId: `ns=${ns};s=${loop}.Tune`,
                                  inputArguments: args("", NaN, "") });
        out.viewer_tune = r.statusCode.name;
        out.viewer_message = (r.outputArguments || []).map((a) => a.value);
    } catch (err) {
        out.viewer_tune = text(err);
    }
    try {
        const w = await vs.write({ nodeId: `ns=${ns};s=${loop}.TBSY`, attributeId: AttributeIds.Value,
                                   value: { value: { dataType: DataType.Boolean, value: true } } });
        out.viewer_write = w.name;
    } catch (err) {
        out.viewer_write = text(err);
    }
    await vs.close();
    await v.disconnect();

    // 3. operator over Basic256Sha256 SignAndEncrypt
    const o = client(MessageSecurityMode.SignAndEncrypt, SecurityPolicy.Basic256Sha256);
    const os = await session(o, "operator", operatorPassword);
    const loopNode = `ns=${ns};s=${loop}`;
    const bad = await os.call({ objectId: loopNode, methodId: `${loopNode}.Tune`, inputArguments: args("", -1, "") });
    out.invalid = { status: bad.statusCode.name, message: bad.outputArguments.map((a) => a.value) };
    const sub = await os.createSubscription2({ requestedPublishingInterval: 50, publishingEnabled: true,
                                               requestedMaxKeepAliveCount: 20, requestedLifetimeCount: 600 });
    const tbsy = [];
    const item = await sub.monitor({ nodeId: `${loopNode}.AutoTuningActive`, attributeId: AttributeIds.Value },
                                   { samplingInterval: 50, discardOldest: true, queueSize: 100 },
                                   TimestampsToReturn.Both);
    item.on("changed", (dv) => tbsy.push(dv.value.value));
    const on = await os.call({ objectId: loopNode, methodId: `${loopNode}.AutoTuningOn`, inputArguments: [] });
    out.on = { status: on.statusCode.name, outputs: on.outputArguments.map((a) => a.value) };
    for (let i = 0; i < 600 && !tbsy.includes(true); i++) await sleep(50);
    const off = await os.call({ objectId: loopNode, methodId: `${loopNode}.AutoTuningOff`, inputArguments: [] });
    out.off = { status: off.statusCode.name, outputs: off.outputArguments.map((a) => a.value) };
    for (let i = 0; i < 600 && tbsy[tbsy.length - 1] !== false; i++) await sleep(50);
    out.tbsy = tbsy;
    const read = async (name) => (await os.read({ nodeId: `${loopNode}.${name}`, attributeIds: AttributeIds.Value })).value.value;
    out.te = await read("TE");
    out.ite = await read("ite");
    out.session = await read("session");
    await sub.terminate();
    await os.close();
    await o.disconnect();
}

main().then(() => {
    console.log(JSON.stringify(out));
    process.exit(0);
}, (err) => {
    console.log(JSON.stringify({ ...out, error: text(err) }));
    process.exit(1);
});
