// motionflows play: keyboard / game pad -> target control over a WebSocket; frames of world
// joints (metres, y up) back; a following perspective camera drawn on a 2D canvas.
// No dependencies. The protocol is documented in motionflows/play/protocol.py.
"use strict";

(() => {
  const canvas = document.getElementById("view");
  const ctx = canvas.getContext("2d");
  const $ = (id) => document.getElementById(id);

  // State the browser test reads (window.playStats); history keeps the last frames.
  const stats = {
    connected: false, frames: 0, errors: 0, errorMessages: [], busy: null,
    latencies: [], history: [], last: null, hello: null, sentControls: 0,
  };
  window.playStats = stats;
  const play = { socket: null, send, stats };
  window.play = play;

  let hello = null;
  let episode = null;
  let paused = false;
  let seq = 0;
  let lastTarget = [0, 0, 0];
  let lastSendTime = 0;
  const sentAt = new Map(); // seq -> page clock (ms) of the key press that sent it
  const arrivals = []; // page clock of recent frame arrivals (stream fps)
  const path = []; // [x, z] of the root
  const footprints = []; // {x, z, angle, side}
  let camera = null; // {x, z, yaw}

  // ------------------------------------------------------------------ socket

  function send(message) {
    if (play.socket && play.socket.readyState === WebSocket.OPEN) {
      play.socket.send(typeof message === "string" ? message : JSON.stringify(message));
      return true;
    }
    return false;
  }

  function showMessage(text) {
    const box = $("message");
    box.hidden = !text;
    box.textContent = text || "";
  }

  let noticeTimer = null;
  function notice(text) {
    $("notice").textContent = text;
    clearTimeout(noticeTimer);
    noticeTimer = setTimeout(() => { $("notice").textContent = ""; }, 4000);
  }

  function connect() {
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    const socket = new WebSocket(`${scheme}://${location.host}/ws`);
    play.socket = socket;
    socket.onopen = () => { stats.connected = true; showMessage(null); };
    socket.onmessage = (event) => {
      let message;
      try { message = JSON.parse(event.data); } catch (err) { return; }
      handle(message);
    };
    socket.onclose = (event) => {
      stats.connected = false;
      if (stats.busy) return; // another page owns the character: stay put, say why
      showMessage(event.code === 1012
        ? "The server stopped. Start `motionflows play` again; this page reconnects."
        : `Disconnected from the server (code ${event.code}); reconnecting…`);
      setTimeout(connect, 1500);
    };
  }

  function handle(message) {
    if (message.type === "hello") {
      hello = stats.hello = message;
      paused = false;
      $("pause").textContent = "Pause";
      $("run").textContent = message.run ? message.run.split("/").slice(-2).join("/") : "";
      const slider = $("temperature");
      [slider.min, slider.max] = message.temperature_range;
      slider.value = message.temperature;
      $("temperature-value").textContent = Number(message.temperature).toFixed(2);
      lastTarget = [NaN, NaN, NaN]; // send the current input at once
      sendTarget(performance.now());
    } else if (message.type === "frame") {
      onFrame(message);
    } else if (message.type === "error") {
      stats.errors += 1;
      stats.errorMessages.push(message.message);
      if (message.fatal) showMessage(message.message);
      else notice(`server: ${message.message}`);
    } else if (message.type === "busy") {
      stats.busy = message.message;
      showMessage(message.message);
    }
  }

  function onFrame(frame) {
    const now = performance.now();
    if (frame.episode !== episode) { // a reset or a new connection: clear the trails
      episode = frame.episode;
      path.length = 0;
      footprints.length = 0;
      support = null;
      camera = null;
    }
    stats.frames += 1;
    stats.last = frame;
    stats.history.push({ t: frame.t, episode: frame.episode, root: frame.root, yaw: frame.yaw,
      joints: frame.joints, ack: frame.ack, arrived: now });
    if (stats.history.length > 600) stats.history.shift();
    for (const [s, sent] of sentAt) { // the first frame that applies control `s`
      if (s <= frame.ack) {
        stats.latencies.push(now - sent);
        sentAt.delete(s);
      }
    }
    if (stats.latencies.length > 500) stats.latencies.splice(0, stats.latencies.length - 500);
    arrivals.push(now);
    while (arrivals.length && arrivals[0] < now - 2000) arrivals.shift();
    const last = path[path.length - 1];
    if (!last || Math.hypot(frame.root[0] - last[0], frame.root[1] - last[1]) > 0.02) {
      path.push(frame.root);
      if (path.length > 4000) path.shift();
    }
    detectFootprints(frame);
    updateHud(frame);
  }

  // ------------------------------------------------------------------- input

  const held = new Set();
  const KEYS = {
    forward: ["KeyW", "ArrowUp", "w", "arrowup"],
    back: ["KeyS", "ArrowDown", "s", "arrowdown"],
    left: ["KeyA", "ArrowLeft", "a", "arrowleft"],
    right: ["KeyD", "ArrowRight", "d", "arrowright"],
    sideLeft: ["KeyQ", "q"],
    sideRight: ["KeyE", "e"],
    run: ["ShiftLeft", "ShiftRight", "shift"],
  };
  const isDown = (name) => KEYS[name].some((k) => held.has(k));
  const STEER = new Set(Object.values(KEYS).flat());

  function keyNames(event) { return [event.code, (event.key || "").toLowerCase()]; }

  window.addEventListener("keydown", (event) => {
    if (event.target && event.target.tagName === "INPUT" && !STEER.has(event.code)) return;
    const names = keyNames(event);
    if (names.some((n) => STEER.has(n))) event.preventDefault();
    if (!event.repeat && event.code === "KeyP") togglePause();
    if (!event.repeat && event.code === "KeyR") send({ type: "reset" });
    names.forEach((n) => n && held.add(n));
    sendTarget(event.timeStamp || performance.now());
  });
  window.addEventListener("keyup", (event) => {
    keyNames(event).forEach((n) => held.delete(n));
    if (!event.shiftKey) KEYS.run.forEach((k) => held.delete(k));
    sendTarget(event.timeStamp || performance.now());
  });
  window.addEventListener("blur", () => { held.clear(); sendTarget(performance.now()); });

  const deadZone = (v) => (Math.abs(v) < 0.15 ? 0 : (v - Math.sign(v) * 0.15) / 0.85);

  function gamepadInput() {
    const pads = navigator.getGamepads ? Array.from(navigator.getGamepads()) : [];
    const pad = pads.find((p) => p && p.connected);
    if (!pad) return null;
    const axis = (i) => deadZone(pad.axes[i] || 0);
    const pressed = (i) => Boolean(pad.buttons[i] && pad.buttons[i].pressed);
    return { y: -axis(1), x: axis(0), turn: axis(2), run: pressed(0) || pressed(7) };
  }

  function currentTarget() {
    if (!hello) return [0, 0, 0];
    const s = hello.speeds;
    const running = isDown("run");
    let forward = 0, sideways = 0, turn = 0;
    if (isDown("forward")) forward += running ? s.run : s.walk;
    if (isDown("back")) forward += s.back * (running ? 1.5 : 1);
    if (isDown("left")) turn += s.turn; // + = counter-clockwise = a left turn
    if (isDown("right")) turn -= s.turn;
    if (isDown("sideLeft")) sideways += s.side * (running ? 1.6 : 1); // + = left
    if (isDown("sideRight")) sideways -= s.side * (running ? 1.6 : 1);
    const pad = gamepadInput();
    if (pad) {
      forward += pad.y > 0 ? pad.y * (pad.run ? s.run : s.walk) : -pad.y * s.back;
      sideways -= pad.x * s.side * (pad.run ? 1.6 : 1);
      turn -= pad.turn * s.turn;
    }
    const lim = hello.limits;
    const clamp = (v, [lo, hi]) => Math.min(hi, Math.max(lo, v));
    return [clamp(forward, lim.forward), clamp(sideways, lim.sideways), clamp(turn, lim.turn)];
  }

  function sendTarget(pressedAt, minInterval = 0) {
    const target = currentTarget();
    const same = target.every((v, i) => Math.abs(v - lastTarget[i]) < 1e-3);
    const now = performance.now();
    if (same || now - lastSendTime < minInterval) return;
    seq += 1;
    const sent = Math.min(pressedAt, now);
    if (send({ type: "control", forward: target[0], sideways: target[1], turn: target[2],
      seq, sent })) {
      sentAt.set(seq, sent);
      lastTarget = target;
      lastSendTime = now;
      stats.sentControls += 1;
    }
  }

  function togglePause() {
    paused = !paused;
    send({ type: "pause", paused });
    $("pause").textContent = paused ? "Resume" : "Pause";
  }
  $("pause").addEventListener("click", togglePause);
  $("reset").addEventListener("click", () => send({ type: "reset" }));
  let temperatureTimer = null;
  $("temperature").addEventListener("input", (event) => {
    const value = Number(event.target.value);
    $("temperature-value").textContent = value.toFixed(2);
    clearTimeout(temperatureTimer);
    temperatureTimer = setTimeout(() => send({ type: "temperature", value }), 60);
  });
  // once set, the slider lets go of the keyboard (the arrows steer, not the slider)
  $("temperature").addEventListener("change", (event) => event.target.blur());
  // buttons must not keep the keyboard focus (Space / Enter would press them again)
  document.querySelectorAll("button, a.button, input").forEach((el) =>
    el.addEventListener("mouseup", () => el.blur()));

  // --------------------------------------------------------------------- HUD

  function percentile(values, q) {
    if (!values.length) return NaN;
    const sorted = [...values].sort((a, b) => a - b);
    return sorted[Math.min(sorted.length - 1, Math.floor(q * sorted.length))];
  }

  function updateHud(frame) {
    const deg = (frame.turn * 180) / Math.PI;
    $("speed").textContent = `${frame.forward.toFixed(2)} m/s forward, ` +
      `${frame.sideways.toFixed(2)} m/s sideways`;
    $("turn").textContent = `${deg.toFixed(0)} °/s`;
    $("model").textContent = `${frame.model_fps.toFixed(0)} frames/s ` +
      `(${frame.model_ms.toFixed(1)} ms a frame), T ${Number(frame.temperature).toFixed(2)}`;
    const fps = arrivals.length > 1
      ? (1000 * (arrivals.length - 1)) / (arrivals[arrivals.length - 1] - arrivals[0]) : 0;
    $("stream").textContent = `${fps.toFixed(1)} fps of ${hello ? hello.fps : "?"}` +
      ` · late ${frame.late} · dropped ${frame.dropped || 0}`;
    const recent = stats.latencies.slice(-50);
    $("latency").textContent = recent.length
      ? `${percentile(recent, 0.5).toFixed(0)} ms median, ` +
        `${percentile(recent, 0.95).toFixed(0)} ms p95 (key to frame)` : "press a key";
  }

  // --------------------------------------------------------- footprints / path

  // A footprint where a foot takes over the support: it becomes the lower foot by 1.5 cm
  // (hysteresis), so a model that skims the floor still leaves alternating prints.
  let support = null;
  function detectFootprints(frame) {
    if (!hello) return;
    const j = frame.joints;
    const [la, lt, ra, rt] = hello.foot_joints; // left ankle, left toe, right ankle, right toe
    const foot = (ankle, toe) => ({
      x: (j[3 * ankle] + j[3 * toe]) / 2,
      z: (j[3 * ankle + 2] + j[3 * toe + 2]) / 2,
      y: Math.min(j[3 * ankle + 1], j[3 * toe + 1]),
      angle: Math.atan2(j[3 * toe] - j[3 * ankle], j[3 * toe + 2] - j[3 * ankle + 2]),
    });
    const left = foot(la, lt), right = foot(ra, rt);
    let now = support;
    if (left.y < right.y - 0.015) now = "left";
    else if (right.y < left.y - 0.015) now = "right";
    if (now && now !== support) {
      const f = now === "left" ? left : right;
      footprints.push({ x: f.x, z: f.z, angle: f.angle, side: now });
      if (footprints.length > 80) footprints.shift();
    }
    support = now;
  }

  // ------------------------------------------------------------------ camera

  function resize() {
    const dpr = window.devicePixelRatio || 1;
    canvas.width = Math.round(canvas.clientWidth * dpr);
    canvas.height = Math.round(canvas.clientHeight * dpr);
  }
  window.addEventListener("resize", resize);
  resize();

  // A camera 3.6 m behind and 1.9 m above the root, looking at the hips, turning with a lag.
  // Lags are time constants (ms), so the camera moves the same at any display rate.
  function makeView(root, yaw, dt) {
    if (!camera) camera = { x: root[0], z: root[1], yaw };
    let dy = yaw - camera.yaw;
    dy = Math.atan2(Math.sin(dy), Math.cos(dy));
    camera.yaw += (1 - Math.exp(-dt / 300)) * dy;
    const follow = 1 - Math.exp(-dt / 60);
    camera.x += follow * (root[0] - camera.x);
    camera.z += follow * (root[1] - camera.z);
    const back = 3.6, height = 1.9;
    const eye = [camera.x - back * Math.sin(camera.yaw), height, camera.z - back * Math.cos(camera.yaw)];
    const look = [camera.x, 0.8, camera.z];
    const f = norm(sub(look, eye));
    const r = norm(cross(f, [0, 1, 0])); // screen right (the character's -x seen from behind)
    const u = cross(r, f);
    const focal = 0.95 * canvas.height;
    return { eye, f, r, u, focal, cx: canvas.width / 2, cy: canvas.height * 0.52, near: 0.1 };
  }
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const norm = (a) => { const n = Math.hypot(...a) || 1; return [a[0] / n, a[1] / n, a[2] / n]; };
  const toCamera = (v, p) => { const d = sub(p, v.eye); return [dot(d, v.r), dot(d, v.u), dot(d, v.f)]; };
  const toScreen = (v, c) => [v.cx + (v.focal * c[0]) / c[2], v.cy - (v.focal * c[1]) / c[2]];

  function line(v, a, b) { // a 3D segment, clipped at the near plane
    let ca = toCamera(v, a), cb = toCamera(v, b);
    if (ca[2] < v.near && cb[2] < v.near) return false;
    if (ca[2] < v.near || cb[2] < v.near) {
      const s = (v.near - ca[2]) / (cb[2] - ca[2]);
      const m = [ca[0] + s * (cb[0] - ca[0]), ca[1] + s * (cb[1] - ca[1]), v.near];
      if (ca[2] < v.near) ca = m; else cb = m;
    }
    const pa = toScreen(v, ca), pb = toScreen(v, cb);
    ctx.moveTo(pa[0], pa[1]);
    ctx.lineTo(pb[0], pb[1]);
    return true;
  }

  // -------------------------------------------------------------------- draw

  function drawGrid(v) {
    const reach = 14, cx = Math.round(camera.x), cz = Math.round(camera.z);
    for (const major of [false, true]) {
      ctx.beginPath();
      for (let k = -reach; k <= reach; k += 1) {
        if ((((cx + k) % 5 === 0)) !== major) continue;
        line(v, [cx + k, 0, cz - reach], [cx + k, 0, cz + reach]);
      }
      for (let k = -reach; k <= reach; k += 1) {
        if ((((cz + k) % 5 === 0)) !== major) continue;
        line(v, [cx - reach, 0, cz + k], [cx + reach, 0, cz + k]);
      }
      ctx.strokeStyle = major ? "#aab4bf" : "#d3d9df";
      ctx.lineWidth = major ? 1.6 : 1;
      ctx.stroke();
    }
  }

  function drawPath(v) {
    if (path.length < 2) return;
    ctx.beginPath();
    for (let i = 1; i < path.length; i += 1) {
      line(v, [path[i - 1][0], 0.005, path[i - 1][1]], [path[i][0], 0.005, path[i][1]]);
    }
    ctx.strokeStyle = "rgba(40, 120, 200, 0.55)";
    ctx.lineWidth = 3;
    ctx.stroke();
  }

  function drawFootprints(v) {
    for (const fp of footprints) {
      const s = Math.sin(fp.angle), c = Math.cos(fp.angle);
      const corner = (a, b) => [fp.x + a * c + b * s, 0.006, fp.z - a * s + b * c];
      const pts = [corner(-0.045, -0.11), corner(0.045, -0.11), corner(0.05, 0.11),
        corner(-0.05, 0.11)].map((p) => toCamera(v, p));
      if (pts.some((p) => p[2] < v.near)) continue;
      ctx.beginPath();
      pts.map((p) => toScreen(v, p)).forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
      ctx.closePath();
      ctx.fillStyle = fp.side === "left" ? "rgba(40, 90, 200, 0.45)" : "rgba(215, 90, 30, 0.45)";
      ctx.fill();
    }
  }

  function drawFigure(v, j) {
    const p = (i) => [j[3 * i], j[3 * i + 1], j[3 * i + 2]];
    const flat = (i) => [j[3 * i], 0.004, j[3 * i + 2]];
    const names = hello.joint_names, parents = hello.parents;
    ctx.lineCap = "round";
    ctx.beginPath(); // shadow
    parents.forEach((q, i) => { if (q >= 0) line(v, flat(q), flat(i)); });
    ctx.strokeStyle = "rgba(0, 0, 0, 0.12)";
    ctx.lineWidth = 5;
    ctx.stroke();
    for (const [prefix, colour] of [["Left", "#2b5fc9"], ["Right", "#d35a1e"], ["", "#333d48"]]) {
      ctx.beginPath();
      parents.forEach((q, i) => {
        const side = names[i].startsWith("Left") ? "Left" : names[i].startsWith("Right") ? "Right" : "";
        if (q >= 0 && side === prefix) line(v, p(q), p(i));
      });
      ctx.strokeStyle = colour;
      ctx.lineWidth = Math.max(2, canvas.height / 180);
      ctx.stroke();
    }
    const head = toCamera(v, p(names.indexOf("Head")));
    if (head[2] > v.near) {
      const [x, y] = toScreen(v, head);
      ctx.beginPath();
      ctx.arc(x, y, (v.focal * 0.09) / head[2], 0, 2 * Math.PI);
      ctx.fillStyle = "#333d48";
      ctx.fill();
    }
  }

  let lastDraw = null;
  function draw(timestamp) {
    const dt = lastDraw === null ? 16 : Math.min(200, timestamp - lastDraw);
    lastDraw = timestamp;
    const frame = stats.last;
    ctx.fillStyle = "#eef1f4";
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    if (frame && hello) {
      const v = makeView(frame.root, frame.yaw, dt);
      drawGrid(v);
      drawPath(v);
      drawFootprints(v);
      drawFigure(v, frame.joints);
      if (paused) {
        ctx.fillStyle = "rgba(29, 39, 51, 0.55)";
        ctx.font = `${Math.round(canvas.height / 14)}px system-ui, sans-serif`;
        ctx.textAlign = "center";
        ctx.fillText("paused", canvas.width / 2, canvas.height * 0.2);
      }
    }
    sendTarget(performance.now(), 30); // the game pad is polled here
    requestAnimationFrame(draw);
  }

  connect();
  requestAnimationFrame(draw);
})();
