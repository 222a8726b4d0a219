// The independent side of the Foxglove live test (NODE_PATH = the npm cache of
// install_node_mcap.sh): node foxglove_check.js ws://HOST:PORT
// connects with @foxglove/ws-protocol's client (retrying while the server
// starts), records serverInfo and the advertised channels, sends one message
// the server must refuse, subscribes to /kestrel/odometry, decodes 3
// messages with @foxglove/rosmsg2-serialization from the advertised schema,
// unsubscribes and prints JSON.
'use strict';
const {FoxgloveClient} = require('@foxglove/ws-protocol');
const WebSocket = require('ws');
const {parse} = require('@foxglove/rosmsg');
const {MessageReader} = require('@foxglove/rosmsg2-serialization');

const url = process.argv[2];
const deadline = Date.now() + 30000;
const out = {
  channels: [],
  messages: [],
  statuses: [],
  subprotocol: null
};
let reader = null, subId = -1;

function finish(code) {
  process.stdout.write(JSON.stringify(out, null, 1) + '\n');
  process.exit(code);
}
setTimeout(() => {
  out.error = 'timed out';
  finish(1);
}, 40000);

function connect() {
  const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
  let opened = false;
  const client = new FoxgloveClient({ws});
  client.on('open', () => {
    opened = true;
    out.subprotocol = ws.protocol;
    ws.send('{"op":"clientPublish"}');  // not offered: a counted, named error
  });
  client.on('error', (e) => {
    if (!opened && Date.now() < deadline) return;  // not listening yet
    out.error = String(e && e.message || e);
  });
  client.on('close', () => {
    if (!opened && Date.now() < deadline)
      setTimeout(connect, 200);
    else if (out.messages.length < 3) {
      out.error = out.error || 'closed early';
      finish(1);
    }
  });
  client.on('serverInfo', (i) => {
    out.serverInfo = i;
  });
  client.on('status', (s) => {
    out.statuses.push(s);
  });
  client.on('advertise', (chans) => {
    for (const c of chans)
      out.channels.push({
        id: c.id,
        topic: c.topic,
        encoding: c.encoding,
        schemaName: c.schemaName,
        schemaEncoding: c.schemaEncoding
      });
    const odom = chans.find((c) => c.topic === '/kestrel/odometry');
    if (!odom) {
      out.error = 'no /kestrel/odometry advertised';
      finish(1);
    }
    reader = new MessageReader(parse(odom.schema, {ros2: true}));
    subId = client.subscribe(odom.id);
  });
  client.on('message', ({subscriptionId, timestamp, data}) => {
    if (subscriptionId !== subId) {
      out.error = 'a message for subscription ' + subscriptionId;
      finish(1);
    }
    const m = reader.readMessage(data);
    out.messages.push({
      timestamp: timestamp.toString(),
      trailing: reader.lastReadHadTrailingBytes(),
      frame_id: m.header.frame_id,
      child_frame_id: m.child_frame_id,
      stamp: m.header.stamp,
      x: m.pose.pose.position.x
    });
    if (out.messages.length === 3) {
      client.unsubscribe(subId);
      setTimeout(() => {
        client.close();
        finish(0);
      }, 300);
    }
  });
}
connect();
