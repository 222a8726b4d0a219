// The independent side of the rosbag2 tests (NODE_PATH = the npm cache of
// install_node_mcap.sh):
//   node mcap_check.js read FILE.mcap   -> JSON on stdout: what @mcap/core reads
//       through the summary and indexes and, separately, record by record with
//       CRCs validated; every message decoded by @foxglove/rosmsg2-serialization
//       and re-encoded by it, to compare with our bytes.
//   node mcap_check.js write FILE.mcap MODE -> a fixture written by @mcap/core
//       and the serializer (MODE lz4 | none | unchunked).
'use strict';
const fs = require('fs');
const {McapIndexedReader, McapStreamReader, McapWriter} = require('@mcap/core');
const {parse} = require('@foxglove/rosmsg');
const {MessageReader, MessageWriter} = require('@foxglove/rosmsg2-serialization');
const fzstd = require('fzstd');
const lz4js = require('lz4js');

const decompressHandlers = {
  zstd: (buf, size) => fzstd.decompress(buf, new Uint8Array(Number(size))),
  lz4: (buf, size) => Uint8Array.from(lz4js.decompress(buf, Number(size))),
};

function summaryOf(msg) {
  // Large arrays (pixels) are summarised; everything else kept.
  return JSON.parse(
      JSON.stringify(
          msg,
          (k, v) => {
            if (ArrayBuffer.isView(v) && !(v instanceof DataView) && v.length <= 64 &&
                !(v instanceof Uint8Array))
              return Array.from(v);  // float64[9] and friends decode as typed arrays
            if (v instanceof Uint8Array || (Array.isArray(v) && v.length > 64)) {
              let sum = 0;
              for (const x of v) sum = (sum + Number(x)) % 4294967296;
              return {length: v.length, sum};
            }
            if (typeof v === 'bigint') return v.toString();
            if (v instanceof Map) return Object.fromEntries([...v.entries()].map(([a, b]) => [String(a), b]));
            return v;
          }),
  );
}

async function read(path) {
  const bytes = new Uint8Array(fs.readFileSync(path));
  const out = {stream: {}, indexed: {}, topics: {}};
  // 1. Record by record, CRCs checked (chunk CRCs, data section CRC, summary CRC).
  const sr = new McapStreamReader({decompressHandlers, validateCrcs: true});
  sr.append(bytes);
  const counts = {};
  const streamMessages = [];
  for (let r; (r = sr.nextRecord());) {
    counts[r.type] = (counts[r.type] || 0) + 1;
    if (r.type === 'Message') streamMessages.push(r);
  }
  out.stream.counts = counts;
  out.stream.done = sr.done();
  // 2. Through the summary: statistics, chunk indexes, message indexes.
  const readable = {
    size: async () => BigInt(bytes.length),
    read: async (o, n) => bytes.subarray(Number(o), Number(o + n)),
  };
  const ir = await McapIndexedReader.Initialize({readable, decompressHandlers});
  out.indexed.profile = ir.header.profile;
  out.indexed.library = ir.header.library;
  out.indexed.chunkIndexes = ir.chunkIndexes.length;
  out.indexed.statistics = ir.statistics ? summaryOf(ir.statistics) : null;
  out.indexed.schemas =
      [...ir.schemasById.values()].map((s) => ({id: s.id, name: s.name, encoding: s.encoding}));
  out.indexed.channels = [...ir.channelsById.values()].map((c) => ({
                                                             id: c.id,
                                                             topic: c.topic,
                                                             messageEncoding: c.messageEncoding,
                                                             schemaId: c.schemaId,
                                                             metadataKeys: [...c.metadata.keys()],
                                                           }));
  out.indexed.metadata = [];
  for await (const m of ir.readMetadata()) out.indexed.metadata.push(m.name);
  const readers = new Map(), writers = new Map();
  for (const [id, c] of ir.channelsById) {
    const s = ir.schemasById.get(c.schemaId);
    const defs = parse(new TextDecoder().decode(s.data), {ros2: true});
    readers.set(id, new MessageReader(defs));
    writers.set(id, new MessageWriter(defs));
  }
  let lastTime = -1n, ordered = true;
  // Chunked files through the chunk and message indexes; an unchunked file has
  // none, so its messages come from the stream reader.
  out.indexed.messagesVia = ir.chunkIndexes.length > 0 ? 'indexes' : 'stream';
  async function* messages() {
    if (ir.chunkIndexes.length > 0)
      yield* ir.readMessages({validateCrcs: true});
    else
      yield* streamMessages;
  }
  for await (const m of messages()) {
    if (m.logTime < lastTime) ordered = false;
    lastTime = m.logTime;
    const c = ir.channelsById.get(m.channelId);
    const t = (out.topics[c.topic] = out.topics[c.topic] || {
      type: ir.schemasById.get(c.schemaId).name,
      count: 0,
      trailing: 0,
      reencodedDiffers: 0,
    });
    const r = readers.get(m.channelId);
    const msg = r.readMessage(m.data);
    if (r.lastReadHadTrailingBytes()) t.trailing++;
    const again = writers.get(m.channelId).writeMessage(msg);
    if (Buffer.compare(Buffer.from(again), Buffer.from(m.data)) !== 0) t.reencodedDiffers++;
    if (t.count === 0) {
      t.first = summaryOf(msg);
      t.firstLogTime = m.logTime.toString();
    }
    t.last = summaryOf(msg);
    t.count++;
    if (t.type === 'sensor_msgs/msg/PointCloud2') {
      // The first points read back through the fields' own offsets, as a viewer would.
      const off = Object.fromEntries(msg.fields.map((f) => [f.name, f.offset]));
      const dv = new DataView(msg.data.buffer, msg.data.byteOffset, msg.data.byteLength);
      const pts = [];
      for (let i = 0; i < Math.min(msg.width, 4); ++i)
        pts.push(['x', 'y', 'z'].map((k) => dv.getFloat32(i * msg.point_step + off[k], !msg.is_bigendian)));
      t.lastPoints = pts;
      if (off.rgb !== undefined) {
        // PCL's packing: the float's bits are 0x00RRGGBB.
        const cols = [];
        for (let i = 0; i < Math.min(msg.width, 4); ++i) {
          const v = dv.getUint32(i * msg.point_step + off.rgb, !msg.is_bigendian);
          cols.push([(v >> 16) & 255, (v >> 8) & 255, v & 255]);
        }
        t.lastColours = cols;
      }
      t.sizeMismatches =
          (t.sizeMismatches || 0) + (msg.data.length !== msg.width * msg.height * msg.point_step);
    }
    if (t.type === 'visualization_msgs/msg/MarkerArray') {
      t.markers = t.markers || [];
      for (const k of msg.markers)
        t.markers.push({
          ns: k.ns,
          id: k.id,
          type: k.type,
          action: k.action,
          frame: k.header.frame_id,
          points: k.points.length,
          firstPoint: k.points[0] || null,
          pose: k.pose,
          scale: k.scale,
          color: k.color
        });
    }
  }
  out.indexed.ordered = ordered;
  process.stdout.write(JSON.stringify(out, null, 1) + '\n');
}

const defs = {
  'sensor_msgs/msg/Imu': `std_msgs/Header header
geometry_msgs/Quaternion orientation
float64[9] orientation_covariance
geometry_msgs/Vector3 angular_velocity
float64[9] angular_velocity_covariance
geometry_msgs/Vector3 linear_acceleration
float64[9] linear_acceleration_covariance
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
================================================================================
MSG: geometry_msgs/Quaternion
float64 x 0
float64 y 0
float64 z 0
float64 w 1
================================================================================
MSG: geometry_msgs/Vector3
float64 x
float64 y
float64 z
`,
  'sensor_msgs/msg/Image': `std_msgs/Header header
uint32 height
uint32 width
string encoding
uint8 is_bigendian
uint32 step
uint8[] data
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
`,
  'sensor_msgs/msg/CameraInfo': `std_msgs/Header header
uint32 height
uint32 width
string distortion_model
float64[] d
float64[9] k
float64[9] r
float64[12] p
uint32 binning_x
uint32 binning_y
sensor_msgs/RegionOfInterest roi
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
================================================================================
MSG: sensor_msgs/RegionOfInterest
uint32 x_offset
uint32 y_offset
uint32 height
uint32 width
bool do_rectify
`,
};

// 0.2 s of a D435i-like stream, stamps from 1.7e9 s: IMU at 200 Hz (gyro x = 0.001 i,
// acc z = 9.81), colour rgb8 4x3 and 16UC1 depth (mm) at 20 Hz, one CameraInfo.
async function write(path, mode) {
  const chunks = [];
  let pos = 0n;
  const writable = {
    position: () => pos,
    write: async (b) => {
      chunks.push(Buffer.from(b));
      pos += BigInt(b.length);
    },
  };
  const w = new McapWriter({
    writable,
    useChunks: mode !== 'unchunked',
    chunkSize: 2048,
    compressChunk: mode === 'lz4' ?
        (d) => ({compression: 'lz4', compressedData: Uint8Array.from(lz4js.compress(d))}) :
        undefined,
  });
  await w.start({profile: 'ros2', library: 'node fixture'});
  const ch = {};
  const ser = {};
  for (const [name, text] of Object.entries(defs)) {
    const sid = await w.registerSchema({name, encoding: 'ros2msg', data: new TextEncoder().encode(text)});
    ser[name] = new MessageWriter(parse(text, {ros2: true}));
    ch[name] = sid;
  }
  const imu = await w.registerChannel(
      {topic: '/cam/imu', messageEncoding: 'cdr', schemaId: ch['sensor_msgs/msg/Imu'], metadata: new Map()});
  const rgb = await w.registerChannel({
    topic: '/cam/color/image_raw',
    messageEncoding: 'cdr',
    schemaId: ch['sensor_msgs/msg/Image'],
    metadata: new Map()
  });
  const dep = await w.registerChannel({
    topic: '/cam/depth/image_rect_raw',
    messageEncoding: 'cdr',
    schemaId: ch['sensor_msgs/msg/Image'],
    metadata: new Map()
  });
  const info = await w.registerChannel({
    topic: '/cam/color/camera_info',
    messageEncoding: 'cdr',
    schemaId: ch['sensor_msgs/msg/CameraInfo'],
    metadata: new Map()
  });
  const t0 = 1700000000n * 1000000000n;
  const stamp = (t) => ({sec: Number(t / 1000000000n), nanosec: Number(t % 1000000000n)});
  let seq = 0;
  const add = async (channelId, t, bytes) =>
      w.addMessage({channelId, sequence: seq++, logTime: t, publishTime: t, data: bytes});
  for (let i = 0; i < 40; i++) {
    const t = t0 + BigInt(i) * 5000000n;
    await add(imu, t, ser['sensor_msgs/msg/Imu'].writeMessage({
      header: {stamp: stamp(t), frame_id: 'imu'},
      orientation: {x: 0, y: 0, z: 0, w: 1},
      orientation_covariance: [-1, 0, 0, 0, 0, 0, 0, 0, 0],
      angular_velocity: {x: 0.001 * i, y: -0.5, z: 0.25},
      angular_velocity_covariance: new Array(9).fill(0),
      linear_acceleration: {x: 0.125, y: 0, z: 9.81},
      linear_acceleration_covariance: new Array(9).fill(0),
    }));
    if (i % 10 === 0) {
      const k = i / 10;
      const px = new Uint8Array(4 * 3 * 3).map((_, j) => (j * 7 + k) & 0xff);
      await add(rgb, t, ser['sensor_msgs/msg/Image'].writeMessage({
        header: {stamp: stamp(t), frame_id: 'color'},
        height: 3,
        width: 4,
        encoding: 'rgb8',
        is_bigendian: 0,
        step: 12,
        data: px,
      }));
      const d = new Uint8Array(4 * 3 * 2);
      const dv = new DataView(d.buffer);
      for (let j = 0; j < 12; j++) dv.setUint16(2 * j, 1000 + 10 * j + k, true);
      await add(dep, t + 1000000n, ser['sensor_msgs/msg/Image'].writeMessage({
        header: {stamp: stamp(t + 1000000n), frame_id: 'color'},
        height: 3,
        width: 4,
        encoding: '16UC1',
        is_bigendian: 0,
        step: 8,
        data: d,
      }));
      await add(info, t, ser['sensor_msgs/msg/CameraInfo'].writeMessage({
        header: {stamp: stamp(t), frame_id: 'color'},
        height: 3,
        width: 4,
        distortion_model: 'plumb_bob',
        d: [0, 0, 0, 0, 0],
        k: [610.5, 0, 2.25, 0, 611.25, 1.5, 0, 0, 1],
        r: [1, 0, 0, 0, 1, 0, 0, 0, 1],
        p: [610.5, 0, 2.25, 0, 0, 611.25, 1.5, 0, 0, 0, 1, 0],
        binning_x: 0,
        binning_y: 0,
        roi: {x_offset: 0, y_offset: 0, height: 0, width: 0, do_rectify: false},
      }));
    }
  }
  await w.end();
  fs.writeFileSync(path, Buffer.concat(chunks));
}

// 0.2 s of a D4xx infrared pair as realsense-ros publishes it without /tf_static:
// IMU at 200 Hz, infra1 and infra2 mono8 4x3 at 20 Hz (infra2 0.5 ms later),
// each with its CameraInfo; infra2's P[3] = -fx * 0.05 (a 5 cm baseline).
async function writeStereo(path) {
  const chunks = [];
  let pos = 0n;
  const writable = {
    position: () => pos,
    write: async (b) => {
      chunks.push(Buffer.from(b));
      pos += BigInt(b.length);
    },
  };
  const w = new McapWriter({writable, useChunks: true, chunkSize: 2048});
  await w.start({profile: 'ros2', library: 'node fixture'});
  const sid = {};
  const ser = {};
  for (const [name, text] of Object.entries(defs)) {
    sid[name] = await w.registerSchema({name, encoding: 'ros2msg', data: new TextEncoder().encode(text)});
    ser[name] = new MessageWriter(parse(text, {ros2: true}));
  }
  const chan = (topic, type) =>
      w.registerChannel({topic, messageEncoding: 'cdr', schemaId: sid[type], metadata: new Map()});
  const imu = await chan('/cam/imu', 'sensor_msgs/msg/Imu');
  const left = await chan('/cam/infra1/image_rect_raw', 'sensor_msgs/msg/Image');
  const right = await chan('/cam/infra2/image_rect_raw', 'sensor_msgs/msg/Image');
  const linfo = await chan('/cam/infra1/camera_info', 'sensor_msgs/msg/CameraInfo');
  const rinfo = await chan('/cam/infra2/camera_info', 'sensor_msgs/msg/CameraInfo');
  const t0 = 1700000000n * 1000000000n;
  const stamp = (t) => ({sec: Number(t / 1000000000n), nanosec: Number(t % 1000000000n)});
  let seq = 0;
  const add = async (channelId, t, bytes) =>
      w.addMessage({channelId, sequence: seq++, logTime: t, publishTime: t, data: bytes});
  const info = (t, frame, tx) => ser['sensor_msgs/msg/CameraInfo'].writeMessage({
    header: {stamp: stamp(t), frame_id: frame},
    height: 3,
    width: 4,
    distortion_model: 'plumb_bob',
    d: [0, 0, 0, 0, 0],
    k: [382.5, 0, 2.0, 0, 382.5, 1.5, 0, 0, 1],
    r: [1, 0, 0, 0, 1, 0, 0, 0, 1],
    p: [382.5, 0, 2.0, tx, 0, 382.5, 1.5, 0, 0, 0, 1, 0],
    binning_x: 0,
    binning_y: 0,
    roi: {x_offset: 0, y_offset: 0, height: 0, width: 0, do_rectify: false},
  });
  const image = (t, frame, k, base) => ser['sensor_msgs/msg/Image'].writeMessage({
    header: {stamp: stamp(t), frame_id: frame},
    height: 3,
    width: 4,
    encoding: 'mono8',
    is_bigendian: 0,
    step: 4,
    data: new Uint8Array(12).map((_, j) => (base + j * 5 + k) & 0xff),
  });
  for (let i = 0; i < 40; i++) {
    const t = t0 + BigInt(i) * 5000000n;
    await add(imu, t, ser['sensor_msgs/msg/Imu'].writeMessage({
      header: {stamp: stamp(t), frame_id: 'imu'},
      orientation: {x: 0, y: 0, z: 0, w: 1},
      orientation_covariance: [-1, 0, 0, 0, 0, 0, 0, 0, 0],
      angular_velocity: {x: 0, y: 0, z: 0},
      angular_velocity_covariance: new Array(9).fill(0),
      linear_acceleration: {x: 0, y: 0, z: 9.81},
      linear_acceleration_covariance: new Array(9).fill(0),
    }));
    if (i % 10 === 0) {
      const k = i / 10;
      await add(left, t, image(t, 'infra1', k, 10));
      await add(right, t + 500000n, image(t + 500000n, 'infra2', k, 100));
      await add(linfo, t, info(t, 'infra1', 0));
      await add(rinfo, t, info(t, 'infra2', -382.5 * 0.05));
    }
  }
  await w.end();
  fs.writeFileSync(path, Buffer.concat(chunks));
}

const [cmd, file, mode] = process.argv.slice(2);
(cmd === 'read' ? read(file) : cmd === 'write-stereo' ? writeStereo(file) : write(file, mode || 'lz4')).catch((e) => {
  process.stderr.write(String(e && e.stack ? e.stack : e) + '\n');
  process.exit(1);
});
