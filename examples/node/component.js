#!/usr/bin/env node
// A CAST component in Node.js, written from proto/cast/v1 and docs/client-protocol.md only.
//
// It reads the launch contract, registers its session (Register + Heartbeat), registers the schema
// of what it writes, watches google.protobuf.StringValue entries of its SA, adds some, proposes a
// task to its SA's task manager, waits for the decision, and completes the task. Each step prints
// one line ("step: what"). Then it exits 0, or with CAST_ARGS {"stay": true} keeps printing what it
// sees until SIGTERM. Other args: "count" (entries to add first, default 1), "text" (their text),
// "every" (with stay: seconds between further entries; default 0, none).
//
// Left out to stay short: reconnecting (a broken session or stream makes it exit 1; `cast run`
// restarts it) and resuming watches; docs/client-protocol.md says how a full client does both.
//
// Needs: `npm ci` here, and the schema of what it writes as a FileDescriptorSet made by protoc
// (`make node` does both; by hand: protoc --include_imports --descriptor_set_out=generated/entry-types.binpb
// google/protobuf/wrappers.proto). proto-loader's own descriptors cannot serve: it merges every file
// of a package into one made-up file, which the server would refuse or, worse, take in place of the
// real google/protobuf/*.proto files other languages register.
'use strict';

const crypto = require('crypto');
const fs = require('fs');
const os = require('os');
const path = require('path');
const grpc = require('@grpc/grpc-js');
const protoLoader = require('@grpc/proto-loader');

const LOAD_OPTIONS = { keepCase: true, longs: String, enums: String, defaults: true, oneofs: true };
const STRING_VALUE = 'google.protobuf.StringValue';
const CALL_DEADLINE_MS = 30000;

function say(step, text) {
  console.log(`${step}: ${text}`);
}

function quit(message, code) {
  console.error(`error: ${message}`);
  process.exit(code);
}

// ------------------------------------------------------------------ launch contract

function readContract(env) {
  const missing = ['CAST_ENDPOINT', 'CAST_COMPONENT_ID', 'CAST_SUBARCHITECTURE'].filter((name) => !env[name]);
  if (!env.CAST_TOKEN && !env.CAST_TOKEN_FILE) missing.push('CAST_TOKEN or CAST_TOKEN_FILE');
  if (missing.length) {
    quit(`missing launch environment: ${missing.join(', ')}; start the component with \`cast run CONFIG\`, `
      + 'or set the variables `cast token` prints', 2);
  }
  let args;
  try {
    args = JSON.parse(env.CAST_ARGS || '{}');
  } catch (err) {
    quit(`CAST_ARGS is not valid JSON: ${err.message}`, 2);
  }
  if (args === null || typeof args !== 'object' || Array.isArray(args)) quit('CAST_ARGS must be a JSON object', 2);
  return { endpoint: env.CAST_ENDPOINT, id: env.CAST_COMPONENT_ID, sa: env.CAST_SUBARCHITECTURE, args };
}

// TLS when CAST_TLS_CA is set (never a fallback to plaintext), with a client certificate when given.
function channelCredentials(env) {
  const { CAST_TLS_CA: ca, CAST_TLS_CERT: cert, CAST_TLS_KEY: key } = env;
  if (Boolean(cert) !== Boolean(key)) quit('set CAST_TLS_CERT and CAST_TLS_KEY together, or neither', 2);
  if (cert && !ca) quit('CAST_TLS_CERT and CAST_TLS_KEY need CAST_TLS_CA (the CA of the servers)', 2);
  if (!ca) return grpc.credentials.createInsecure();
  const read = (file) => fs.readFileSync(file);
  return grpc.credentials.createSsl(read(ca), key ? read(key) : null, cert ? read(cert) : null);
}

function channelOptions(env) {
  // docs/client-protocol.md, "Reconnection": short reconnect backoff, keepalive to notice dead peers.
  const options = {
    'grpc.initial_reconnect_backoff_ms': 100,
    'grpc.min_reconnect_backoff_ms': 100,
    'grpc.max_reconnect_backoff_ms': 2000,
    'grpc.keepalive_time_ms': 10000,
    'grpc.keepalive_timeout_ms': 5000,
  };
  if (env.CAST_TLS_SERVER_NAME) options['grpc.ssl_target_name_override'] = env.CAST_TLS_SERVER_NAME;
  return options;
}

// The token sent with every call: CAST_TOKEN, or the newest one in CAST_TOKEN_FILE, which the
// orchestrator rewrites with a fresh token before the old one expires.
class Token {
  constructor(env) {
    this.value = env.CAST_TOKEN || '';
    this.file = env.CAST_TOKEN_FILE || '';
    this.stamp = '';
    this.checked = 0;
    if (this.file) {
      // The file is the token when it is set (the renewed one): empty or unreadable at start is an error, as in
      // the Python, C++ and Java runners, not a silent fall-back to CAST_TOKEN.
      let text = '';
      let problem = 'is empty';
      try {
        text = fs.readFileSync(this.file, 'utf8').trim();
      } catch {
        problem = 'cannot be read';
      }
      if (!text) {
        quit(`CAST_TOKEN_FILE names ${this.file}, which ${problem}: point it at a token file (\`cast run\` renews `
          + 'one per component), or unset it', 2);
      }
      this.reload(true);
    }
  }

  // Look at the file (modification time and size) at most once a second.
  current() {
    if (this.file && Date.now() - this.checked >= 1000) this.reload(false);
    return this.value;
  }

  // Re-read the file; true if the token changed. An empty or unreadable file keeps the last token.
  reload(force) {
    if (!this.file) return false;
    this.checked = Date.now();
    try {
      const stat = fs.statSync(this.file);
      const stamp = `${stat.mtimeMs}/${stat.size}`;
      if (!force && stamp === this.stamp) return false;
      this.stamp = stamp;
      const text = fs.readFileSync(this.file, 'utf8').trim();
      if (!text || text === this.value) return false;
      this.value = text;
      return true;
    } catch (err) {
      return false;
    }
  }

  metadata() {
    const metadata = new grpc.Metadata();
    metadata.set('authorization', `Bearer ${this.current()}`);
    return metadata;
  }
}

// Directory.AwaitRun until it answers OK: each call has a 1 s deadline, DEADLINE_EXCEEDED means
// "not yet", UNAVAILABLE "ask again shortly" (docs/client-protocol.md, Start-up, step 5).
async function awaitRun(directory, token) {
  for (;;) {
    try {
      return await new Promise((resolve, reject) => {
        directory.AwaitRun({}, token.metadata(), { deadline: Date.now() + 1000 },
          (err, response) => (err ? reject(err) : resolve(response)));
      });
    } catch (err) {
      if (err.code === grpc.status.UNAVAILABLE) await new Promise((resolve) => setTimeout(resolve, 200));
      else if (err.code !== grpc.status.DEADLINE_EXCEEDED) throw Object.assign(err, { call: 'AwaitRun' });
    }
  }
}

// A unary call with the token and a deadline. UNAUTHENTICATED: re-read the token file and, if the
// token changed, send the call once more (the token is checked before anything is applied).
function unary(client, method, request, token) {
  const send = typeof method === 'string' ? client[method].bind(client) : method;
  const name = typeof method === 'string' ? method : method.name;
  const once = () => new Promise((resolve, reject) => {
    send(request, token.metadata(), { deadline: Date.now() + CALL_DEADLINE_MS },
      (err, response) => (err ? reject(err) : resolve(response)));
  });
  return once()
    .catch((err) => {
      if (err.code === grpc.status.UNAUTHENTICATED && token.reload(true)) return once();
      throw err;
    })
    .catch((err) => {
      throw Object.assign(err, { call: name }); // so that the error message names the call
    });
}

// Values that arrive on streams, awaited by key in whatever order they come.
class Inbox {
  constructor() {
    this.values = new Map();
    this.waiters = new Map();
  }

  put(key, value) {
    const waiter = this.waiters.get(key);
    if (waiter) {
      this.waiters.delete(key);
      waiter(value);
    } else {
      this.values.set(key, value);
    }
  }

  take(key) {
    if (this.values.has(key)) {
      const value = this.values.get(key);
      this.values.delete(key);
      return Promise.resolve(value);
    }
    return new Promise((resolve) => this.waiters.set(key, resolve));
  }
}

// ------------------------------------------------------------------ entry types and schemas

function loadEntryTypes(file) {
  if (!fs.existsSync(file)) quit(`no schema file ${file}: run \`make node\` in the CAST repository`, 2);
  const descriptorSet = fs.readFileSync(file);
  const types = protoLoader.loadFileDescriptorSetFromBuffer(descriptorSet, LOAD_OPTIONS);
  return { descriptorSet, types };
}

function pack(types, typeName, value) {
  return { type_url: `type.googleapis.com/${typeName}`, value: types[typeName].serialize(value) };
}

function unpack(types, any) {
  const typeName = any.type_url.slice(any.type_url.lastIndexOf('/') + 1);
  return types[typeName] ? types[typeName].deserialize(any.value) : null;
}

// RegisterSchemasRequest is {files = 1: FileDescriptorSet}. The set protoc wrote is already
// serialized, and an embedded message is encoded like bytes (tag, length, content), so the request
// is the set with a tag and its length in front: the server gets the files byte for byte.
function registerSchemas(directory, descriptorSet, token) {
  const length = [];
  let n = descriptorSet.length;
  for (; n >= 128; n = Math.floor(n / 128)) length.push((n % 128) | 128);
  length.push(n);
  const request = Buffer.concat([Buffer.from([0x0a, ...length]), descriptorSet]);
  const method = directory.constructor.service.RegisterSchemas;
  function RegisterSchemas(req, metadata, options, callback) {
    return directory.makeUnaryRequest(
      method.path, (bytes) => bytes, method.responseDeserialize, req, metadata, options, callback);
  }
  return unary(directory, RegisterSchemas, request, token);
}

// ------------------------------------------------------------------ the component

async function main() {
  // SIGTERM (cast run stopping the system) or Ctrl-C: stop cleanly, with exit code 0.
  let shutdown = (code) => process.exit(code);
  process.on('SIGTERM', () => shutdown(0));
  process.on('SIGINT', () => shutdown(0));
  const env = process.env;
  const me = readContract(env);
  const token = new Token(env);
  const protoDir = env.CAST_PROTO_DIR || path.join(__dirname, '..', '..', 'proto');
  const api = grpc.loadPackageDefinition(protoLoader.loadSync(
    ['cast/v1/directory.proto', 'cast/v1/working_memory.proto', 'cast/v1/task_manager.proto'],
    { ...LOAD_OPTIONS, includeDirs: [protoDir] })).cast.v1;
  const { descriptorSet, types } = loadEntryTypes(
    env.CAST_ENTRY_TYPES || path.join(__dirname, 'generated', 'entry-types.binpb'));
  const count = Number(me.args.count ?? 1);
  if (!Number.isInteger(count) || count < 1) quit(`CAST_ARGS: count must be a whole number >= 1, not ${me.args.count}`, 2);
  const text = String(me.args.text ?? `hello from ${me.id}`);
  const credentials = channelCredentials(env);
  const options = channelOptions(env);
  say('contract', `${me.id} in ${me.sa} at ${me.endpoint} (${env.CAST_TLS_CA ? 'TLS' : 'plaintext'}), `
    + `args ${JSON.stringify(me.args)}`);

  // Route the SA to the server hosting it: the directory's own channel when it is the same server.
  let directory = new api.Directory(me.endpoint, credentials, options);
  const system = await unary(directory, 'DescribeSystem', {}, token);
  const hosted = system.subarchitectures.find((sa) => sa.name === me.sa);
  const endpoint = hosted && hosted.endpoint && hosted.endpoint !== system.endpoint ? hosted.endpoint : me.endpoint;
  if (endpoint !== me.endpoint) {
    directory.close();
    directory = new api.Directory(endpoint, credentials, options);
  }
  const shared = { ...options, channelOverride: directory.getChannel() };
  const wm = new api.WorkingMemory(endpoint, credentials, shared);
  const tm = new api.TaskManager(endpoint, credentials, shared);
  say('system', `'${system.name}': ${me.sa} is served at ${endpoint}`);

  let stopping = false;
  const streams = [];
  const lost = (what) => (err) => {
    if (!stopping) quit(`${what} ended (${grpc.status[err.code]}: ${err.details}); exiting so that cast run `
      + 'starts the component again', 1);
  };

  // The session: Register, then heartbeats every lease / 3 on one stream; it ends with the stream.
  const session = await unary(directory, 'Register',
    { language: 'node', kind: 'managed', pid: process.pid, host: os.hostname() }, token);
  const heartbeat = directory.Heartbeat(token.metadata());
  streams.push(heartbeat);
  let state = 'COMPONENT_STATE_STARTING';
  const beat = () => heartbeat.write({ session_id: session.session_id, state });
  beat();
  const beating = setInterval(beat, Math.max(100, session.lease_ms / 3));
  heartbeat.on('data', () => {});
  heartbeat.on('error', lost('the session (heartbeat stream)'));
  say('registered', `session ${session.session_id}, lease ${session.lease_ms} ms`);

  const inbox = new Inbox();
  const decisions = tm.Decisions({}, token.metadata());
  streams.push(decisions);
  decisions.on('data', (task) => inbox.put(`task ${task.task_id}`, task));
  decisions.on('error', lost('the decision stream'));

  const stop = (code) => {
    if (stopping) return;
    stopping = true;
    state = 'COMPONENT_STATE_STOPPING';
    beat();
    clearInterval(beating);
    for (const stream of streams) stream.cancel();
    for (const client of [wm, tm, directory]) client.close();
    say('stopped', `exit code ${code}`);
    process.exit(code);
  };
  shutdown = stop;

  const registered = await registerSchemas(directory, descriptorSet, token);
  if (!registered.types.includes(STRING_VALUE)) quit(`the schema file does not define ${STRING_VALUE}`, 2);
  say('schemas', `registered ${registered.types.length} types, ${STRING_VALUE} among them`);

  // One Watch stream; the watch is in place once the server answers `created`.
  const watch = wm.Watch(token.metadata());
  streams.push(watch);
  watch.on('error', lost('the watch stream'));
  watch.on('data', (response) => {
    if (response.created) inbox.put(`watch ${response.created.watch_id}`, { ok: true });
    if (response.failed) inbox.put(`watch ${response.failed.watch_id}`, { ok: false, ...response.failed });
    for (const event of response.events) {
      const value = event.entry && unpack(types, event.entry.value);
      say('saw', `${event.operation.replace('OPERATION_', '')} ${event.address.id} by ${event.source_component} `
        + `(revision ${event.revision}): ${JSON.stringify(value ? value.value : null)}`);
      if (event.source_component === me.id) inbox.put(`event ${event.address.id}`, event);
    }
  });
  watch.write({ create: { watch_id: 1, filters: [{ subarchitecture: me.sa, type: STRING_VALUE, include_entry: true }] } });
  const created = await inbox.take('watch 1');
  if (!created.ok) quit(`the watch was refused: ${created.code}: ${created.message}`, 1);
  say('watching', `${STRING_VALUE} entries of ${me.sa} (watch 1)`);
  if (process.env.CAST_START_BARRIER === '1') {
    // Started by `cast run`: say so, and begin work only once every component of the system has
    // started, so that their watches see this component's first writes (the start barrier).
    state = 'COMPONENT_STATE_STARTED';
    beat();
    await awaitRun(directory, token);
    say('released', 'every component of the system has started');
  }
  state = 'COMPONENT_STATE_RUNNING';
  beat();

  // Add an entry, and wait until the watch has brought it back.
  let added = 0;
  const greet = async () => {
    added += 1;
    const id = `${me.id}-${crypto.randomBytes(4).toString('hex')}`;
    const written = await unary(wm, 'Add',
      { address: { id, subarchitecture: me.sa }, value: pack(types, STRING_VALUE, { value: `${text} #${added}` }) },
      token);
    say('added', `${id} (revision ${written.revision}, version ${written.version})`);
    await inbox.take(`event ${id}`);
    return id;
  };
  let last = '';
  for (let i = 0; i < count; i += 1) last = await greet();

  // Propose a task; the decision comes with the response or later on the Decisions stream.
  const proposed = await unary(tm, 'Propose',
    { name: 'read-back', data: pack(types, STRING_VALUE, { value: last }), priority: 0 }, token);
  let task = proposed.task;
  say('proposed', `task ${task.task_id} '${task.name}' (${task.state})`);
  if (task.state === 'TASK_STATE_WAITING') task = await inbox.take(`task ${task.task_id}`);
  if (task.state !== 'TASK_STATE_ADOPTED') {
    say('rejected', `task ${task.task_id}: ${task.reason}`);
    return stop(1);
  }
  say('adopted', `task ${task.task_id}`);
  // The task's work: read the last entry back.
  const { entry } = await unary(wm, 'Get', { address: { id: last, subarchitecture: me.sa } }, token);
  say('read', `${last}: ${JSON.stringify(unpack(types, entry.value).value)} by ${entry.author}`);
  await unary(tm, 'Complete',
    { task_id: task.task_id, outcome: 'TASK_OUTCOME_SUCCEEDED', reason: `read ${last} back` }, token);
  say('completed', `task ${task.task_id} (SUCCEEDED)`);

  if (me.args.stay) {
    const every = Number(me.args.every || 0);
    if (every > 0) setInterval(() => greet().catch(failed), every * 1000);
    say('done', `running until SIGTERM${every > 0 ? `, adding an entry every ${every} s` : ''}`);
    return undefined; // the streams keep the process alive; SIGTERM calls stop(0)
  }
  say('done', 'all steps finished');
  return stop(0);
}

function failed(err) {
  quit(err.call ? `${err.call}: ${grpc.status[err.code]}: ${err.details}` : err.stack, 1);
}

main().catch(failed);
