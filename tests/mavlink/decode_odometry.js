// Decodes a file of MAVLink frames (minimal.xml and common.xml messages) with node-mavlink (an implementation
// independent of ours) and prints what it found, one fact per line, for
// tests/mavlink/test_mavlink_odometry.cpp to compare field by field:
//   pkt I seq sysid compid msgid payload_len crc_in_frame crc_node_computed
//   field I NAME V[,V...]
//   reserialized I HEX          (node-mavlink's own encoding of the decoded message)
//   stats valid N invalid N unknown N
// Usage: node decode_odometry.js FRAMES.bin
'use strict';
const fs = require('fs');
const { Readable } = require('stream');
const { MavLinkPacketSplitter, MavLinkPacketParser, MavLinkProtocolV2, minimal, common } = require('node-mavlink');
const { x25crc } = require('mavlink-mappings');

const bytes = fs.readFileSync(process.argv[2]);
const splitter = new MavLinkPacketSplitter();
const parser = new MavLinkPacketParser();
let index = 0;
const fmt = (v) => (Array.isArray(v) ? v.map(fmt).join(',') : typeof v === 'bigint' ? v.toString() : String(v));

parser.on('data', (packet) => {
  const h = packet.header;
  const clazz = common.REGISTRY[h.msgid] || minimal.REGISTRY[h.msgid];
  const frame = packet.buffer;
  const crcIn = frame.readUInt16LE(frame.length - 2);
  const crcNode = x25crc(frame, 1, 2, clazz ? clazz.MAGIC_NUMBER : 0);
  console.log(`pkt ${index} ${h.seq} ${h.sysid} ${h.compid} ${h.msgid} ${h.payloadLength} ${crcIn} ${crcNode}`);
  if (clazz) {
    const data = packet.protocol.data(packet.payload, clazz);
    for (const f of clazz.FIELDS) console.log(`field ${index} ${f.source} ${fmt(data[f.name])}`);
    const again = new MavLinkProtocolV2(h.sysid, h.compid).serialize(data, h.seq);
    console.log(`reserialized ${index} ${again.toString('hex')}`);
  }
  index++;
});
parser.on('end', () => {
  console.log(`stats valid ${splitter._validPackagesCount} invalid ${splitter._invalidPackagesCount} unknown ${splitter._unknownPackagesCount}`);
});
Readable.from([bytes]).pipe(splitter).pipe(parser);
