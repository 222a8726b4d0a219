// MAVLink 2 signing by an implementation independent of ours (node-mavlink's
// MavLinkProtocolV2.sign and MavLinkPacketSignature), for
// tests/mavlink/test_mavlink_imu.cpp:
//   node signing_check.js sign KEYHEX OUT.bin UNIX_MS LINK_ID
//     writes signed HIGHRES_IMU, TIMESYNC, COMMAND_ACK and COMMAND_LONG frames (sysid 1, compid 1), frame i
//     signed at UNIX_MS + i ms; prints "frame I MSGID TIMESTAMP" per frame.
//   node signing_check.js verify KEYHEX IN.bin
//     prints "pkt I MSGID SYSID COMPID SIGNED LINK_ID TIMESTAMP MATCH" per frame (MATCH 1 when the signature
//     is the one node computes with KEYHEX), then "field I NAME VALUE" for its fields.
'use strict';
const fs = require('fs');
const { Readable } = require('stream');
const { MavLinkPacketSplitter, MavLinkPacketParser, MavLinkProtocolV2, minimal, common } = require('node-mavlink');

const [mode, keyHex, file] = process.argv.slice(2);
const key = Buffer.from(keyHex, 'hex');
if (key.length !== 32) throw new Error('key must be 64 hex digits');
const fmt = (v) => (Array.isArray(v) ? v.map(fmt).join(',') : typeof v === 'bigint' ? v.toString() : String(v));

if (mode === 'sign') {
  const unixMs = Number(process.argv[5]);
  const linkId = Number(process.argv[6]);
  const proto = new MavLinkProtocolV2(1, 1, MavLinkProtocolV2.IFLAG_SIGNED);
  const imu = new common.HighresImu();
  imu.timeUsec = 123456789n;
  imu.xacc = 0.5; imu.yacc = -0.25; imu.zacc = -9.75;
  imu.xgyro = 0.125; imu.ygyro = -0.0625; imu.zgyro = 1.5;
  imu.temperature = 31.5;
  imu.fieldsUpdated = 0x3f;
  const ts = new common.TimeSync();
  ts.tc1 = 5000000000n; ts.ts1 = 42n; ts.targetSystem = 1; ts.targetComponent = 197;
  const ack = new common.CommandAck();
  ack.command = 511; ack.result = 0; ack.targetSystem = 1; ack.targetComponent = 197;
  const cmd = new common.CommandLong();
  cmd.command = 511; cmd._param1 = 105; cmd._param2 = 5000; cmd.targetSystem = 1; cmd.targetComponent = 1;
  const out = [];
  [imu, ts, ack, cmd].forEach((m, i) => {
    const signed = proto.sign(proto.serialize(m, i), linkId, key, unixMs + i);
    out.push(signed);
    console.log(`frame ${i} ${m.constructor.MSG_ID} ${signed.readUIntLE(signed.length - 12, 6)}`);
  });
  fs.writeFileSync(file, Buffer.concat(out));
} else if (mode === 'verify') {
  const splitter = new MavLinkPacketSplitter();
  const parser = new MavLinkPacketParser();
  let index = 0;
  parser.on('data', (packet) => {
    const h = packet.header;
    const s = packet.signature;
    const signed = (h.incompatibilityFlags & MavLinkProtocolV2.IFLAG_SIGNED) !== 0 && s !== null;
    const match = signed && s.matches(key) ? 1 : 0;
    console.log(`pkt ${index} ${h.msgid} ${h.sysid} ${h.compid} ${signed ? 1 : 0} ${signed ? s.linkId : -1} ` +
                `${signed ? s.timestamp : -1} ${match}`);
    const clazz = common.REGISTRY[h.msgid] || minimal.REGISTRY[h.msgid];
    if (clazz) {
      const data = packet.protocol.data(packet.payload, clazz);
      for (const f of clazz.FIELDS) console.log(`field ${index} ${f.source} ${fmt(data[f.name])}`);
    }
    index++;
  });
  Readable.from([fs.readFileSync(file)]).pipe(splitter).pipe(parser);
} else {
  throw new Error('usage: signing_check.js sign|verify KEYHEX FILE ...');
}
