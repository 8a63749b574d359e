// An independent OPC UA client (node-opcua) for tests/opcua: connects to the endpoint given
// (security None, anonymous: the allow_insecure server), finds the cell's GMS object, calls
// ResultManagement.GetLatestResult and prints one line "CELLCTL-RESULT <JSON>" (what the test checks).
import { OPCUAClient, MessageSecurityMode, SecurityPolicy, DataType } from "node-opcua";

const [endpoint, cellId] = process.argv.slice(2);
const client = OPCUAClient.create({
  securityMode: MessageSecurityMode.None,
  securityPolicy: SecurityPolicy.None,
  endpointMustExist: false,
  connectionStrategy: { maxRetry: 2, initialDelay: 200 },
});
const out = {};
try {
  await client.connect(endpoint);
  const session = await client.createSession();
  try {
    const ns = (await session.readNamespaceArray());
    const app = ns.indexOf(`urn:cellctl:opcua:${cellId}`);
    const gmsNs = ns.indexOf("http://opcfoundation.org/UA/GMS/");
    const resNs = ns.indexOf("http://opcfoundation.org/UA/Machinery/Result/");
    const cell = `ns=${app};s=cell-${cellId}`;
    const typeDef = await session.browse({ nodeId: cell, referenceTypeId: "HasTypeDefinition", browseDirection: 0 });
    out.type = typeDef.references[0].browseName.toString();
    const path = async (start, names) => {
      const r = await session.translateBrowsePath({
        startingNode: start,
        relativePath: { elements: names.map(([nsi, name]) => ({
          referenceTypeId: "i=33", isInverse: false, includeSubtypes: true,
          targetName: { namespaceIndex: nsi, name } })) },
      });
      return r.targets[0].targetId.toString();
    };
    const rm = await path(cell, [[gmsNs, "ResultManagement"]]);
    const method = await path(rm, [[resNs, "GetLatestResult"]]);
    const res = await session.call({ objectId: rm, methodId: method,
      inputArguments: [{ dataType: DataType.Int32, value: 1000 }] });
    out.status = res.statusCode.name;
    const [handle, result, error] = res.outputArguments.map((v) => v.value);
    out.handle = handle;
    out.error = error;
    // node-opcua 2.186 leaves this companion-model structure undecoded (an OpaqueStructure, also
    // after promoteOpaqueStructure): the test checks its type and size; docs/opcua.md
    out.resultType = result.constructor.name;
    out.resultBytes = result.buffer ? result.buffer.length : -1;
  } finally {
    await session.close();
  }
} catch (err) {
  out.failure = String(err && err.stack || err);
} finally {
  await client.disconnect();
}
console.log("CELLCTL-RESULT " + JSON.stringify(out));
