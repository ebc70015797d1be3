#!/usr/bin/env node
// Test client for a Foxglove WebSocket server (subprotocol foxglove.websocket.v1).
// Subscribes to channels, decodes ROS 2 CDR (ros2msg schemas) and JSON messages, and writes one
// JSON object per line. See README.md for the options and the output format.
import fs from "node:fs";
import net from "node:net";
import { parseArgs } from "node:util";

import wsProtocol from "@foxglove/ws-protocol";
import { parse as parseMessageDefinition } from "@foxglove/rosmsg";
import { MessageReader } from "@foxglove/rosmsg2-serialization";
import WebSocket from "ws";

// @foxglove/ws-protocol is CommonJS whose named exports Node cannot detect: use the default.
const { FoxgloveClient } = wsProtocol;

const USAGE = `usage: node client.mjs --url ws://HOST:PORT [options]
  --topics all|T1,T2,...      channels to subscribe to (default all; '*' globs allowed)
  --duration-s S              stop S seconds after process start (default: until server closes)
  --out FILE                  write JSON lines to FILE (default stdout)
  --connect-after-s D         wait D seconds before connecting
  --pause-after-s A --pause-s P
                              A s after the connection opens, stop reading the socket for P s
  --pause-from-topic T        count A from the first message of topic T instead (a run whose
                              start the server holds back until the client subscribed)
  --get-params all|N1,N2,...  getParameters (id "get-params") after serverInfo
  --set NAME=VALUE            setParameters (id "set-params"); repeatable; VALUE parsed as JSON
                              when possible, else a string; NAME:float64=V etc. sets the type
  --subscribe-params N1,N2    subscribeParameterUpdates
  --connection-graph          subscribeConnectionGraph (if the server has the capability)
  --socket-fd N               use the already-connected TCP socket inherited as fd N (made by the
                              caller, e.g. with a small SO_RCVBUF) instead of connecting; --url
                              still gives the Host header and path
  --subprotocols P1,P2        subprotocols offered in the handshake (default
                              foxglove.websocket.v1,foxglove.sdk.v1; the server picks one)
  --help`;

// ---------------------------------------------------------------------------------------------
// Arguments

function fail(message) {
  process.stderr.write(`client.mjs: ${message}\n${USAGE}\n`);
  process.exit(2);
}

let args;
try {
  ({ values: args } = parseArgs({
    options: {
      url: { type: "string" },
      topics: { type: "string", default: "all" },
      "duration-s": { type: "string" },
      out: { type: "string" },
      "pause-after-s": { type: "string" },
      "pause-s": { type: "string" },
      "pause-from-topic": { type: "string" },
      "connect-after-s": { type: "string" },
      "get-params": { type: "string" },
      set: { type: "string", multiple: true, default: [] },
      "subscribe-params": { type: "string" },
      "connection-graph": { type: "boolean", default: false },
      subprotocols: { type: "string" },
      "socket-fd": { type: "string" },
      help: { type: "boolean", default: false },
    },
    strict: true,
    allowPositionals: false,
  }));
} catch (err) {
  fail(err.message);
}
if (args.help) {
  process.stdout.write(`${USAGE}\n`);
  process.exit(0);
}
if (!args.url) fail("--url is required");

function seconds(name) {
  const raw = args[name];
  if (raw === undefined) return undefined;
  const value = Number(raw);
  if (!Number.isFinite(value) || value < 0) fail(`--${name} must be a non-negative number`);
  return value;
}
const durationS = seconds("duration-s");
const connectAfterS = seconds("connect-after-s") ?? 0;
const pauseAfterS = seconds("pause-after-s");
const pauseS = seconds("pause-s");
if ((pauseAfterS === undefined) !== (pauseS === undefined)) {
  fail("--pause-after-s and --pause-s go together");
}

function splitList(raw) {
  return raw
    .split(",")
    .map((s) => s.trim())
    .filter((s) => s.length > 0);
}

// Topic filter: "all" or a list of exact names / '*' globs.
const topicFilter = (() => {
  const list = splitList(args.topics);
  if (list.length === 0 || list.includes("all")) return () => true;
  const exact = new Set(list.filter((t) => !t.includes("*")));
  const globs = list
    .filter((t) => t.includes("*"))
    .map((t) => new RegExp(`^${t.split("*").map(escapeRegExp).join(".*")}$`));
  return (topic) => exact.has(topic) || globs.some((re) => re.test(topic));
})();
function escapeRegExp(s) {
  return s.replace(/[.+?^${}()|[\]\\]/g, "\\$&");
}

const getParamNames =
  args["get-params"] === undefined
    ? undefined
    : args["get-params"].trim() === "all"
      ? []
      : splitList(args["get-params"]);
const subscribeParamNames =
  args["subscribe-params"] === undefined ? undefined : splitList(args["subscribe-params"]);

// Foxglove SDK servers (foxglove-sdk, foxglove_bridge >= 3) only accept "foxglove.sdk.v1", which is
// the same wire protocol as "foxglove.websocket.v1" under a new name; offer both by default.
const subprotocols =
  args.subprotocols === undefined
    ? [FoxgloveClient.SUPPORTED_SUBPROTOCOL, "foxglove.sdk.v1"]
    : splitList(args.subprotocols);
if (subprotocols.length === 0) fail("--subprotocols needs at least one name");

let socketFd;
if (args["socket-fd"] !== undefined) {
  socketFd = Number(args["socket-fd"]);
  if (!Number.isInteger(socketFd) || socketFd < 0) fail("--socket-fd must be a file descriptor");
}

const PARAM_TYPES = new Set(["float64", "float64_array", "byte_array"]);
const setParameters = args.set.map((spec) => {
  const eq = spec.indexOf("=");
  if (eq <= 0) fail(`--set expects NAME=VALUE, got ${JSON.stringify(spec)}`);
  let name = spec.slice(0, eq);
  const raw = spec.slice(eq + 1);
  let type;
  const colon = name.lastIndexOf(":");
  if (colon > 0 && PARAM_TYPES.has(name.slice(colon + 1))) {
    type = name.slice(colon + 1);
    name = name.slice(0, colon);
  }
  let value;
  try {
    value = JSON.parse(raw);
  } catch {
    value = raw;
  }
  return type === undefined ? { name, value } : { name, value, type };
});

// ---------------------------------------------------------------------------------------------
// Output: JSON lines, batched so that kHz message rates cost few write() calls.

const hrtime = process.hrtime.bigint;
// Wall clock with sub-millisecond resolution: the wall time of process start (fractional ms)
// advanced by the monotonic clock.
function wallNs() {
  return BigInt(Math.round((performance.timeOrigin + performance.now()) * 1e3)) * 1000n;
}

class LineWriter {
  constructor(stream) {
    this.stream = stream;
    this.parts = [];
    this.size = 0;
    this.timer = undefined;
    this.failed = false;
    stream.on("error", (err) => {
      // e.g. EPIPE when the reader went away: stop writing, keep running to a clean exit.
      this.failed = true;
      process.stderr.write(`client.mjs: output error: ${err.message}\n`);
    });
  }

  write(obj) {
    obj.t_ns = hrtime().toString();
    obj.wall_ns = wallNs().toString();
    const line = `${JSON.stringify(obj)}\n`;
    this.parts.push(line);
    this.size += line.length;
    if (this.size >= 1 << 16) {
      this.flush();
    } else if (this.timer === undefined) {
      this.timer = setTimeout(() => this.flush(), 20);
    }
  }

  flush() {
    if (this.timer !== undefined) {
      clearTimeout(this.timer);
      this.timer = undefined;
    }
    if (this.parts.length === 0) return;
    const chunk = this.parts.join("");
    this.parts = [];
    this.size = 0;
    if (!this.failed) this.stream.write(chunk);
  }

  end() {
    this.flush();
    return new Promise((resolve) => {
      if (this.failed) {
        resolve();
      } else if (this.stream === process.stdout) {
        this.stream.write("", () => resolve());
      } else {
        this.stream.end(() => resolve());
      }
    });
  }
}

const out = new LineWriter(
  args.out === undefined ? process.stdout : fs.createWriteStream(args.out, { flags: "w" }),
);

// ---------------------------------------------------------------------------------------------
// Decoding

// Plain-JSON view of a decoded message: BigInt -> Number when safe else string, typed arrays ->
// arrays, non-finite floats -> "NaN" / "Infinity" / "-Infinity" (JSON has no such numbers).
function toPlain(value) {
  switch (typeof value) {
    case "bigint":
      return bigintToPlain(value);
    case "number":
      return Number.isFinite(value) ? value : String(value);
    case "object": {
      if (value === null) return null;
      if (Array.isArray(value)) return value.map(toPlain);
      if (ArrayBuffer.isView(value)) {
        if (value instanceof DataView) {
          return Array.from(new Uint8Array(value.buffer, value.byteOffset, value.byteLength));
        }
        const result = new Array(value.length);
        for (let i = 0; i < value.length; i++) result[i] = toPlain(value[i]);
        return result;
      }
      const result = {};
      for (const key of Object.keys(value)) result[key] = toPlain(value[key]);
      return result;
    }
    default:
      return value;
  }
}
function bigintToPlain(v) {
  const n = Number(v);
  return Number.isSafeInteger(n) ? n : v.toString();
}

const textDecoder = new TextDecoder();

// Returns a decode(DataView) function for a channel; throws if the channel cannot be decoded.
function makeDecoder(channel) {
  if (channel.encoding === "cdr") {
    if (channel.schemaEncoding !== "ros2msg") {
      throw new Error(`unsupported schemaEncoding ${JSON.stringify(channel.schemaEncoding)} for cdr`);
    }
    const definitions = parseMessageDefinition(channel.schema, { ros2: true });
    const reader = new MessageReader(definitions);
    return (data) => toPlain(reader.readMessage(data));
  }
  if (channel.encoding === "json") {
    return (data) => JSON.parse(textDecoder.decode(data));
  }
  throw new Error(`unsupported message encoding ${JSON.stringify(channel.encoding)}`);
}

// ---------------------------------------------------------------------------------------------
// State

const channels = new Map(); // channelId -> { channel, decoder | undefined, decoderError, subId }
const subscriptions = new Map(); // subscriptionId -> channel entry
const counts = {}; // topic -> messages received
let decodeErrors = 0;
let unknownSubscriptionMessages = 0;
let totalMessages = 0;

let ws;
let client;
let opened = false;
let closed = false;
let stopping = false;
let stopReason;
let paused = false;
let pauseScheduled = false;
const timers = [];

function later(seconds, fn) {
  const timer = setTimeout(fn, seconds * 1000);
  timers.push(timer);
  return timer;
}

const LEVEL_NAMES = { 0: "info", 1: "warning", 2: "error" };

// ---------------------------------------------------------------------------------------------
// Connection

function connect() {
  if (stopping) return;
  // No permessage-deflate: Foxglove servers do not use it, and it keeps the receive path simple.
  const options = { perMessageDeflate: false };
  if (socketFd !== undefined) {
    options.createConnection = () => new net.Socket({ fd: socketFd, readable: true, writable: true });
  }
  ws = new WebSocket(args.url, subprotocols, options);
  client = new FoxgloveClient({ ws });

  client.on("open", () => {
    opened = true;
    out.write({ type: "open", url: args.url, protocol: ws.protocol });
    if (pauseAfterS !== undefined && args["pause-from-topic"] === undefined) {
      later(pauseAfterS, pauseReading);
    }
  });

  client.on("error", (err) => {
    out.write({ type: "error", message: String(err?.message ?? err) });
  });

  client.on("close", (event) => {
    closed = true;
    out.write({
      type: "close",
      code: event?.code,
      reason: event?.reason ?? "",
      byClient: stopping,
    });
    stop(opened ? "serverClose" : "connectFailed");
  });

  client.on("serverInfo", (info) => {
    out.write({
      type: "serverInfo",
      name: info.name,
      capabilities: info.capabilities,
      supportedEncodings: info.supportedEncodings,
      metadata: info.metadata,
      sessionId: info.sessionId,
    });
    afterServerInfo(info).catch((err) => {
      out.write({ type: "error", message: `after serverInfo: ${err?.message ?? err}` });
    });
  });

  client.on("status", (msg) => {
    const line = { type: "status", level: msg.level, levelName: LEVEL_NAMES[msg.level], message: msg.message };
    if (msg.id !== undefined) line.id = msg.id;
    out.write(line);
  });

  client.on("removeStatus", (msg) => {
    out.write({ type: "removeStatus", statusIds: msg.statusIds });
  });

  client.on("advertise", (newChannels) => {
    out.write({
      type: "advertise",
      channels: newChannels.map((c) => {
        const item = {
          id: c.id,
          topic: c.topic,
          encoding: c.encoding,
          schemaName: c.schemaName,
          schemaEncoding: c.schemaEncoding,
          schemaLength: typeof c.schema === "string" ? c.schema.length : 0,
        };
        if (c.metadata !== undefined) item.metadata = c.metadata;
        return item;
      }),
    });
    for (const channel of newChannels) addChannel(channel);
  });

  client.on("unadvertise", (channelIds) => {
    out.write({ type: "unadvertise", channelIds });
    for (const id of channelIds) {
      const entry = channels.get(id);
      if (entry === undefined) continue;
      channels.delete(id);
      // The server drops the subscription itself; forget it here.
      if (entry.subId !== undefined) subscriptions.delete(entry.subId);
    }
  });

  client.on("message", (event) => {
    const entry = subscriptions.get(event.subscriptionId);
    if (entry === undefined) {
      unknownSubscriptionMessages++;
      return;
    }
    const topic = entry.channel.topic;
    const logTimeNs = event.timestamp.toString();
    totalMessages++;
    counts[topic] = (counts[topic] ?? 0) + 1;
    let data;
    try {
      if (entry.decoder === undefined) throw entry.decoderError;
      data = entry.decoder(event.data);
    } catch (err) {
      decodeErrors++;
      out.write({
        type: "decodeError",
        topic,
        channelId: entry.channel.id,
        logTimeNs,
        error: String(err?.message ?? err),
      });
      return;
    }
    if (pauseAfterS !== undefined && topic === args["pause-from-topic"] && !pauseScheduled) {
      pauseScheduled = true;
      later(pauseAfterS, pauseReading);
    }
    out.write({
      type: "message",
      topic,
      channelId: entry.channel.id,
      logTimeNs,
      bytes: event.data.byteLength,
      data,
    });
  });

  client.on("time", (event) => {
    out.write({ type: "time", timestampNs: event.timestamp.toString() });
  });

  client.on("parameterValues", (event) => {
    const line = { type: "parameterValues" };
    if (event.id !== undefined) line.id = event.id;
    line.parameters = event.parameters.map((p) => {
      const item = { name: p.name, value: p.value };
      if (p.type !== undefined) item.type = p.type;
      return item;
    });
    out.write(line);
    const waiter = parameterWaiters.get(event.id);
    if (waiter !== undefined) {
      parameterWaiters.delete(event.id);
      waiter();
    }
  });

  client.on("connectionGraphUpdate", (event) => {
    const { op: _op, ...rest } = event;
    out.write({ type: "connectionGraph", ...rest });
  });

  client.on("advertiseServices", (services) => {
    out.write({
      type: "advertiseServices",
      services: services.map((s) => ({ id: s.id, name: s.name, type: s.type })),
    });
  });

  client.on("unadvertiseServices", (serviceIds) => {
    out.write({ type: "unadvertiseServices", serviceIds });
  });
}

function addChannel(channel) {
  let entry = channels.get(channel.id);
  if (entry === undefined) {
    entry = { channel, decoder: undefined, decoderError: undefined, subId: undefined };
    channels.set(channel.id, entry);
  } else {
    entry.channel = channel; // re-advertised: keep the subscription, refresh the decoder
  }
  try {
    entry.decoder = makeDecoder(channel);
    entry.decoderError = undefined;
  } catch (err) {
    entry.decoder = undefined;
    entry.decoderError = err instanceof Error ? err : new Error(String(err));
  }
  if (entry.subId === undefined && topicFilter(channel.topic)) {
    entry.subId = client.subscribe(channel.id);
    subscriptions.set(entry.subId, entry);
    counts[channel.topic] ??= 0;
  }
}

// Parameter requests, in order: getParameters, then (after its reply, or 2 s) setParameters.
const parameterWaiters = new Map(); // request id -> resolve
function waitForParameterReply(id, timeoutS) {
  return new Promise((resolve) => {
    const timer = setTimeout(() => {
      parameterWaiters.delete(id);
      out.write({ type: "notice", message: `no parameterValues reply with id ${id} within ${timeoutS} s` });
      resolve();
    }, timeoutS * 1000);
    parameterWaiters.set(id, () => {
      clearTimeout(timer);
      resolve();
    });
  });
}

async function afterServerInfo(info) {
  const caps = info.capabilities ?? [];
  const wantsParams =
    getParamNames !== undefined || setParameters.length > 0 || subscribeParamNames !== undefined;
  if (wantsParams && !caps.includes("parameters")) {
    out.write({ type: "notice", message: "server does not advertise the parameters capability" });
  } else if (wantsParams) {
    if (subscribeParamNames !== undefined) {
      if (caps.includes("parametersSubscribe")) {
        client.subscribeParameterUpdates(subscribeParamNames);
      } else {
        out.write({ type: "notice", message: "server does not advertise parametersSubscribe" });
      }
    }
    if (getParamNames !== undefined) {
      const reply = waitForParameterReply("get-params", 2);
      client.getParameters(getParamNames, "get-params");
      await reply;
    }
    if (setParameters.length > 0 && !stopping) {
      const reply = waitForParameterReply("set-params", 2);
      client.setParameters(setParameters, "set-params");
      await reply;
    }
  }
  if (args["connection-graph"]) {
    if (caps.includes("connectionGraph")) client.subscribeConnectionGraph();
    else out.write({ type: "notice", message: "server does not advertise connectionGraph" });
  }
}

// ---------------------------------------------------------------------------------------------
// Pausing: ws.pause() pauses the net.Socket and stops ws from resuming it when its receiver
// drains, so nothing more is read from the kernel; the TCP window closes and the server's queue
// for this client fills up.

function pauseReading() {
  if (stopping || closed || ws.readyState !== WebSocket.OPEN) return;
  ws.pause();
  paused = true;
  out.write({ type: "paused", socketBytesRead: ws._socket?.bytesRead });
  later(pauseS, resumeReading);
}

function resumeReading() {
  if (!paused) return;
  paused = false;
  if (ws.readyState === WebSocket.OPEN || ws.readyState === WebSocket.CLOSING) ws.resume();
  out.write({ type: "resumed", socketBytesRead: ws._socket?.bytesRead });
}

// ---------------------------------------------------------------------------------------------
// Stopping

async function stop(reason) {
  if (stopping) {
    if (reason === "serverClose" || reason === "connectFailed") finish();
    return;
  }
  stopping = true;
  stopReason = reason;
  for (const timer of timers) clearTimeout(timer);
  if (ws === undefined || closed || ws.readyState === WebSocket.CLOSED) {
    finish();
    return;
  }
  if (paused) resumeReading(); // so that the close handshake can be read
  // Close handshake; fall back to dropping the TCP connection if the server does not answer.
  setTimeout(() => {
    if (!closed) {
      out.write({ type: "notice", message: "close handshake timed out, terminating" });
      ws.terminate();
      setTimeout(finish, 200);
    }
  }, 1000);
  try {
    if (ws.readyState === WebSocket.CONNECTING) ws.terminate();
    else ws.close(1000, "client stop"); // FoxgloveClient.close() would send no status code
  } catch (err) {
    out.write({ type: "error", message: `close: ${err?.message ?? err}` });
    finish();
  }
}

let finished = false;
async function finish() {
  if (finished) return;
  finished = true;
  out.write({
    type: "summary",
    reason: stopReason,
    counts,
    decodeErrors,
    messages: totalMessages,
    unknownSubscriptionMessages,
    connected: opened,
  });
  await out.end();
  // Exit 1 only when no connection was ever made, 3 on an internal error.
  process.exit(internalError ? 3 : opened ? 0 : 1);
}

let internalError = false;
process.on("uncaughtException", (err) => {
  // A bug in this client: report it as a line and exit 3 rather than dying without a summary.
  internalError = true;
  out.write({ type: "error", message: `internal: ${err?.stack ?? err}` });
  if (!stopping) stopReason = "internalError";
  finish(); // no-op if already finishing; the exit status is 3 either way
});
process.on("SIGTERM", () => stop("signal"));
process.on("SIGINT", () => stop("signal"));

if (durationS !== undefined) setTimeout(() => stop("duration"), durationS * 1000);
if (connectAfterS > 0) later(connectAfterS, connect);
else connect();
