// snds app: draw demonstrations, train a stable policy on them, push it around.
// Plain JavaScript, no build step and no library: everything the page does goes through the
// server's JSON API (see the README), which this file uses as any other client would.
"use strict";

(() => {
  const DEFAULT_VIEW = { x0: -100, x1: 100, y0: -75, y1: 75 };
  const FIELD_SIZE = [72, 54];
  // The grid of the field previewed while a job trains (computed in the training process).
  const PREVIEW_SIZE = [48, 36];
  const SETTINGS = ["steps", "seed", "rollouts", "samples"];
  const canvas = document.getElementById("canvas");
  const ctx = canvas.getContext("2d");
  const $ = (id) => document.getElementById(id);

  // Everything the page knows; exposed as window.sndsApp for the browser test and for curious users.
  const app = {
    view: { ...DEFAULT_VIEW },
    strokes: [], // raw strokes as drawn: arrays of [x, y, t] (page units, seconds)
    target: null, // [x, y] once dragged; else the first stroke's end
    mode: "draw",
    limits: null,
    jobs: { snds: null, bc: null }, // {id, status, result, field, layer}
    showBC: false,
    drawing: null,
    dragging: null, // "target" or "point"
    rollout: null,
    drawn: { snds: false, bc: false },
    timings: {},
    settings: {},
    // A stroke added after training refines the shown policy (POST /api/jobs/{id}/refine):
    // the job doing so, shown in place of the policy once its field is drawn.
    refining: null,
    // What undo restores after such a stroke: {strokes: count before it, jobs, drawn}.
    history: [],
  };
  window.sndsApp = app;

  const params = new URLSearchParams(location.search);
  for (const name of SETTINGS) {
    if (params.has(name)) app.settings[name] = parseInt(params.get(name), 10);
  }

  // --- Coordinates --------------------------------------------------------------------------

  function size() {
    const rect = canvas.getBoundingClientRect();
    return { w: rect.width, h: rect.height };
  }
  function toPixels([x, y]) {
    const { w, h } = size();
    const v = app.view;
    return [((x - v.x0) / (v.x1 - v.x0)) * w, ((v.y1 - y) / (v.y1 - v.y0)) * h];
  }
  function toWorld(px, py) {
    const { w, h } = size();
    const v = app.view;
    return [v.x0 + (px / w) * (v.x1 - v.x0), v.y1 - (py / h) * (v.y1 - v.y0)];
  }
  function eventWorld(event) {
    const rect = canvas.getBoundingClientRect();
    return toWorld(event.clientX - rect.left, event.clientY - rect.top);
  }
  function pixelDistance(a, b) {
    const [ax, ay] = toPixels(a);
    const [bx, by] = toPixels(b);
    return Math.hypot(ax - bx, ay - by);
  }
  app.toPixels = toPixels;

  // --- Strokes ------------------------------------------------------------------------------

  function target() {
    if (app.target) return app.target;
    if (!app.strokes.length) return null;
    const first = app.strokes[0];
    return first[first.length - 1].slice(0, 2);
  }

  // The stroke as it is trained on: its end moved onto the target by a ramp that is zero at its
  // start (the server does the same; so does snds train for ends that differ).
  function ramped(stroke) {
    const goal = target();
    const [ex, ey] = stroke[stroke.length - 1];
    const t0 = stroke[0][2];
    const span = stroke[stroke.length - 1][2] - t0;
    return stroke.map(([x, y, t]) => {
      const s = (t - t0) / span;
      return [x + s * (goal[0] - ex), y + s * (goal[1] - ey)];
    });
  }

  function strokesBody() {
    return { strokes: app.strokes, target: target() };
  }

  function strokesChanged() {
    if (app.refining) cancelRefinement();
    app.history = [];
    app.jobs = { snds: null, bc: null };
    app.drawn = { snds: false, bc: false };
    app.rollout = null;
    $("bc").checked = app.showBC = false;
    setMode("draw");
    showMetrics();
    progress(0, "not trained");
    updateButtons();
    draw();
  }

  // --- Server -------------------------------------------------------------------------------

  async function api(path, body, { method = "POST", raw = false, type = "application/json" } = {}) {
    const options = { method };
    if (body !== undefined) {
      options.body = type === "application/json" ? JSON.stringify(body) : body;
      options.headers = { "Content-Type": type };
    }
    let response;
    try {
      response = await fetch(path, options);
    } catch (error) {
      throw new Error("cannot reach the snds server (is snds app still running?)");
    }
    if (!response.ok) {
      let reason = `${response.status} ${response.statusText}`;
      try {
        reason = (await response.json()).error || reason;
      } catch (error) { /* not JSON */ }
      throw new Error(reason);
    }
    return raw ? response : response.json();
  }

  function say(text, error = false) {
    const status = $("status");
    status.textContent = text;
    status.classList.toggle("error", error);
  }

  function progress(fraction, label) {
    $("bar").style.width = `${Math.round(100 * Math.max(0, Math.min(1, fraction)))}%`;
    $("progress-label").textContent = label;
  }

  // A job's progress, kept with it and shown while it is the one the BC box selects.
  function jobProgress(job, fraction, label) {
    job.progress = [fraction, label];
    if (labelJob() === job) progress(fraction, label);
  }

  function showProgress() {
    const job = labelJob();
    if (job && job.progress) progress(...job.progress);
    else progress(0, "not trained");
  }

  // --- Training -----------------------------------------------------------------------------

  let stream = null;

  async function train(method) {
    if (!app.strokes.length) return;
    if (stream) stream.close();
    if (app.refining) cancelRefinement();
    app.history = [];
    for (const other of Object.values(app.jobs)) {
      if (other && !["done", "error", "cancelled"].includes(other.status.state)) other.status.state = "cancelled";
    }
    app.jobs[method] = null;
    app.drawn[method] = false;
    showMetrics(); // the check's numbers of the policy before go with it
    document.body.dataset.state = "training";
    app.timings[method] = { clicked: performance.now() };
    progress(0, `${method.toUpperCase()}: starting`);
    updateButtons();
    let status;
    try {
      const v = app.view;
      const preview = { bounds: [v.x0, v.x1, v.y0, v.y1], size: PREVIEW_SIZE };
      status = await api("/api/train", { ...strokesBody(), method, settings: app.settings, preview });
    } catch (error) {
      say(error.message, true);
      progress(0, "not trained");
      document.body.dataset.state = "error";
      updateButtons();
      return;
    }
    const job = { id: status.id, method, status };
    app.jobs[method] = job;
    say(`Training ${method === "bc" ? "behavioural cloning (no guarantee)" : "a stable policy"}...`);
    watch(job);
  }

  function watch(job) {
    stream = new EventSource(`/api/jobs/${job.id}/events`);
    const mine = stream;
    mine.onmessage = (message) => {
      const status = JSON.parse(message.data);
      if (app.jobs[job.method] !== job && app.refining !== job) {
        mine.close();
        return;
      }
      job.status = status;
      const name = job.method.toUpperCase() + (job.refines ? " refined" : "");
      if (status.state === "training") {
        const total = status.total || 1;
        const loss = status.loss == null ? "" : `, loss ${status.loss.toExponential(2)}`;
        const doing = job.refines ? `${job.method.toUpperCase()}: refining with the new stroke,` : `${name}:`;
        jobProgress(job, status.step / total, `${doing} step ${status.step} of ${status.total || "?"}${loss}`);
        if ((status.previews || 0) > (job.previews || 0) && !job.result) loadPreview(job, status.previews);
      } else if (status.state === "checking") {
        jobProgress(job, 1, `${name}: trained; checking stability...`);
      }
      if (status.result && !job.result) {
        job.result = status.result;
        loadField(job);
      }
      if (status.state === "done") {
        // The job's time is training, then the stability check (and saving): say which is which.
        const training = status.metrics && status.metrics.train_seconds;
        const split = training == null ? ` in ${status.seconds.toFixed(1)} s` : `: ${training.toFixed(1)} s training + ${(status.seconds - training).toFixed(1)} s check`;
        const short = training == null ? "" : `${training.toFixed(1)} s + ${(status.seconds - training).toFixed(1)} s check`;
        jobProgress(job, 1, job.refines ? `${name}: ${short}` : `${name}: done${split}`);
        say(job.method === "bc"
          ? "BC trained: click to start it anywhere, and compare."
          : job.refines
            ? "Refined with the new stroke. Draw another to refine again; Undo goes back."
            : "Trained. Click anywhere to start the policy; drag the moving point to push it.");
        showMetrics();
      } else if (status.state === "error") {
        jobProgress(job, 0, `${name}: failed`);
        say(job.refines ? `Refining failed: ${status.error} (Undo removes the stroke)` : status.error, true);
        if (app.refining === job) {
          app.refining = null;
          document.body.dataset.state = "trained";
          draw();
        } else document.body.dataset.state = "error";
      }
      if (["done", "error", "cancelled"].includes(status.state)) {
        mine.close();
        if (stream === mine) stream = null;
      }
      updateButtons();
    };
    mine.onerror = () => {
      if (mine.readyState === EventSource.CLOSED || stream !== mine) return;
      mine.close();
      say("lost the connection to the snds server while training", true);
      progress(0, "not trained");
      updateButtons();
    };
  }

  // The field of the policy while it trains: drawn until the saved model's field replaces it
  // (it does not enable Run: only a saved model is rolled out).
  async function loadPreview(job, count) {
    job.previews = count;
    let preview;
    try {
      preview = await api(`/api/jobs/${job.id}/preview`, undefined, { method: "GET" });
    } catch (error) {
      return; // the job moved on (saved, cancelled): its own field or state follows
    }
    if (job.result || app.jobs[job.method] !== job) return;
    job.preview = preview;
    job.previewLayer = renderLayer(job, preview);
    draw();
  }

  async function loadField(job) {
    const v = app.view;
    try {
      job.field = await api(`/api/jobs/${job.id}/field`, {
        bounds: [v.x0, v.x1, v.y0, v.y1],
        size: FIELD_SIZE,
      });
    } catch (error) {
      say(error.message, true);
      return;
    }
    if (app.jobs[job.method] !== job && app.refining !== job) return;
    const before = performance.now();
    job.layer = renderLayer(job);
    job.layerMs = performance.now() - before;
    if (app.refining === job) {
      // The refined policy takes the board: the rollout of the policy before goes with it.
      app.refining = null;
      app.jobs[job.method] = job;
      app.rollout = null;
      rolloutToken += 1;
      app.timings.refine.drawn = performance.now();
    } else {
      app.timings[job.method].drawn = performance.now();
    }
    app.drawn[job.method] = true;
    // After a refinement the board stays in Draw mode: the next stroke refines again.
    if (currentJob() === job && !job.refines) setMode("run");
    document.body.dataset.state = "trained";
    updateButtons();
    draw();
  }

  // --- The field: V contours and streamlines, drawn once per job into an offscreen layer ----

  function sampler(field) {
    const { x, y } = field;
    const nx = x.length;
    const ny = y.length;
    // Bilinear interpolation of a grid value (row j = y[j], column i = x[i]).
    return (grid, px, py) => {
      const fx = ((px - x[0]) / (x[nx - 1] - x[0])) * (nx - 1);
      const fy = ((py - y[0]) / (y[ny - 1] - y[0])) * (ny - 1);
      if (fx < 0 || fy < 0 || fx > nx - 1 || fy > ny - 1) return null;
      const i = Math.min(nx - 2, Math.floor(fx));
      const j = Math.min(ny - 2, Math.floor(fy));
      const a = fx - i;
      const b = fy - j;
      const at = (jj, ii) => grid[jj][ii];
      const mix = (p, q, s) => (Array.isArray(p) ? p.map((pk, k) => pk + s * (q[k] - pk)) : p + s * (q - p));
      return mix(mix(at(j, i), at(j, i + 1), a), mix(at(j + 1, i), at(j + 1, i + 1), a), b);
    };
  }

  function renderLayer(job, field = job.field) {
    const { w, h } = size();
    const ratio = window.devicePixelRatio || 1;
    const layer = document.createElement("canvas");
    layer.width = Math.round(w * ratio);
    layer.height = Math.round(h * ratio);
    const g = layer.getContext("2d");
    const sample = sampler(field);
    if (field.V) drawContours(g, field, layer.width, layer.height);
    g.scale(ratio, ratio);
    drawStreamlines(g, field, sample, job.method === "bc" ? "rgba(150, 40, 40, 0.5)" : "rgba(30, 50, 80, 0.5)");
    return layer;
  }

  // Filled bands of log V with a darker pixel where the band changes: contour lines. The grid
  // spans the view, so each pixel maps straight onto it (rows of the grid go up, the canvas's
  // down); plain loops over typed arrays keep a full-size board to some tens of milliseconds.
  function drawContours(g, field, width, height) {
    const nx = field.x.length;
    const ny = field.y.length;
    const logV = new Float64Array(nx * ny);
    field.V.forEach((row, j) => row.forEach((v, i) => { logV[j * nx + i] = Math.log(Math.max(v, 1e-300)); }));
    let hi = -Infinity;
    let lo = Infinity;
    for (const v of logV) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
    lo = Math.max(lo, hi - 14); // 14 e-folds of V are enough to see its shape near the target
    const bands = 16;
    const scale = bands / Math.max(hi - lo, 1e-12);
    const band = new Int16Array(width * height);
    for (let py = 0; py < height; py++) {
      const fy = (1 - py / (height - 1)) * (ny - 1);
      const j = Math.min(ny - 2, Math.floor(fy));
      const b = fy - j;
      for (let px = 0; px < width; px++) {
        const fx = (px / (width - 1)) * (nx - 1);
        const i = Math.min(nx - 2, Math.floor(fx));
        const a = fx - i;
        const k = j * nx + i;
        const top = logV[k] + a * (logV[k + 1] - logV[k]);
        const bottom = logV[k + nx] + a * (logV[k + nx + 1] - logV[k + nx]);
        const value = top + b * (bottom - top);
        band[py * width + px] = Math.max(0, Math.min(bands - 1, Math.floor((value - lo) * scale)));
      }
    }
    const image = g.createImageData(width, height);
    const data = image.data;
    for (let p = 0; p < band.length; p++) {
      const k = band[p];
      const s = k / (bands - 1);
      const right = p % width < width - 1 ? band[p + 1] : k;
      const down = p + width < band.length ? band[p + width] : k;
      const edge = right !== k || down !== k;
      data[4 * p] = 246 - 70 * s - (edge ? 60 : 0);
      data[4 * p + 1] = 250 - 45 * s - (edge ? 50 : 0);
      data[4 * p + 2] = 255 - 20 * s - (edge ? 30 : 0);
      data[4 * p + 3] = 255;
    }
    g.putImageData(image, 0, 0);
  }

  function drawStreamlines(g, field, sample, color) {
    const v = app.view;
    const cells = 64;
    const cw = (v.x1 - v.x0) / cells;
    const ch = (v.y1 - v.y0) / Math.round((cells * 3) / 4);
    const rows = Math.round((cells * 3) / 4);
    const taken = new Uint8Array(cells * rows);
    const cell = ([x, y]) => {
      const i = Math.floor((x - v.x0) / cw);
      const j = Math.floor((y - v.y0) / ch);
      return i < 0 || j < 0 || i >= cells || j >= rows ? -1 : j * cells + i;
    };
    const step = 0.4 * cw;
    const direction = (p, sign) => {
      const u = sample(field.velocity, p[0], p[1]);
      if (!u) return null;
      const n = Math.hypot(u[0], u[1]);
      return n < 1e-12 ? null : [(sign * u[0]) / n, (sign * u[1]) / n];
    };
    const trace = (start, sign) => {
      const points = [start];
      let p = start;
      for (let k = 0; k < 400; k++) {
        const d1 = direction(p, sign);
        if (!d1) break;
        const mid = [p[0] + 0.5 * step * d1[0], p[1] + 0.5 * step * d1[1]];
        const d2 = direction(mid, sign);
        if (!d2) break;
        p = [p[0] + step * d2[0], p[1] + step * d2[1]];
        const c = cell(p);
        if (c < 0 || (taken[c] && k > 1)) break;
        points.push(p);
      }
      return points;
    };
    let seed = 12345;
    const random = () => ((seed = (seed * 16807) % 2147483647) / 2147483647);
    const seeds = [];
    for (let j = 0; j < 18; j++) for (let i = 0; i < 24; i++) {
      seeds.push([v.x0 + ((i + random()) / 24) * (v.x1 - v.x0), v.y0 + ((j + random()) / 18) * (v.y1 - v.y0)]);
    }
    g.strokeStyle = color;
    g.fillStyle = color;
    g.lineWidth = 1;
    for (const s of seeds) {
      if (taken[cell(s)]) continue;
      const line = trace(s, -1).reverse().concat(trace(s, 1).slice(1));
      if (line.length < 6) continue;
      for (const p of line) { const c = cell(p); if (c >= 0) taken[c] = 1; }
      g.beginPath();
      line.forEach((p, k) => { const [px, py] = toPixels(p); k ? g.lineTo(px, py) : g.moveTo(px, py); });
      g.stroke();
      const m = Math.floor(line.length / 2);
      const [ax, ay] = toPixels(line[m]);
      const [bx, by] = toPixels(line[Math.min(line.length - 1, m + 1)]);
      const angle = Math.atan2(by - ay, bx - ax);
      g.beginPath();
      g.moveTo(bx, by);
      g.lineTo(bx - 6 * Math.cos(angle - 0.45), by - 6 * Math.sin(angle - 0.45));
      g.lineTo(bx - 6 * Math.cos(angle + 0.45), by - 6 * Math.sin(angle + 0.45));
      g.closePath();
      g.fill();
    }
  }

  // --- Drawing the board --------------------------------------------------------------------

  // The job whose field is shown: BC once its field is drawn; until then (BC training) SNDS's
  // stays on the board, and Run keeps working on it.
  function currentJob() {
    const bc = app.jobs.bc;
    return app.showBC && bc && bc.layer ? bc : app.jobs.snds;
  }

  // The job the progress bar speaks for: the one the BC box selects.
  function labelJob() {
    return app.showBC ? app.jobs.bc : app.refining || app.jobs.snds;
  }

  function path(points, { color, width, dash = [] }) {
    if (points.length < 2) return;
    ctx.save();
    ctx.strokeStyle = color;
    ctx.lineWidth = width;
    ctx.setLineDash(dash);
    ctx.lineJoin = ctx.lineCap = "round";
    ctx.beginPath();
    points.forEach((p, k) => { const [px, py] = toPixels(p); k ? ctx.lineTo(px, py) : ctx.moveTo(px, py); });
    ctx.stroke();
    ctx.restore();
  }

  // A stroke's direction: a dot at its start and arrowheads at a third and two thirds of its
  // length (pixels), pointing the way it was drawn.
  function directions(points, color) {
    if (points.length < 2) return;
    const pixels = points.map(toPixels);
    const lengths = [0];
    for (let k = 1; k < pixels.length; k++) {
      lengths.push(lengths[k - 1] + Math.hypot(pixels[k][0] - pixels[k - 1][0], pixels[k][1] - pixels[k - 1][1]));
    }
    const total = lengths[lengths.length - 1];
    ctx.save();
    ctx.fillStyle = color;
    ctx.beginPath();
    ctx.arc(pixels[0][0], pixels[0][1], 4.5, 0, 2 * Math.PI);
    ctx.fill();
    if (total < 30) { ctx.restore(); return; }
    for (const share of [1 / 3, 2 / 3]) {
      const at = share * total;
      let k = 1;
      while (k < pixels.length - 1 && lengths[k] < at) k += 1;
      const [ax, ay] = pixels[k - 1];
      const [bx, by] = pixels[k];
      const s = (at - lengths[k - 1]) / Math.max(1e-9, lengths[k] - lengths[k - 1]);
      const [cx, cy] = [ax + s * (bx - ax), ay + s * (by - ay)];
      const angle = Math.atan2(by - ay, bx - ax);
      ctx.beginPath();
      ctx.moveTo(cx + 6 * Math.cos(angle), cy + 6 * Math.sin(angle));
      ctx.lineTo(cx - 6 * Math.cos(angle - 0.6), cy - 6 * Math.sin(angle - 0.6));
      ctx.lineTo(cx - 6 * Math.cos(angle + 0.6), cy - 6 * Math.sin(angle + 0.6));
      ctx.closePath();
      ctx.fill();
    }
    ctx.restore();
  }

  function star([px, py], radius) {
    ctx.save();
    ctx.beginPath();
    for (let k = 0; k < 10; k++) {
      const r = k % 2 ? radius * 0.45 : radius;
      const a = -Math.PI / 2 + (k * Math.PI) / 5;
      ctx.lineTo(px + r * Math.cos(a), py + r * Math.sin(a));
    }
    ctx.closePath();
    ctx.fillStyle = "#f2c230";
    ctx.strokeStyle = "#8a6a00";
    ctx.lineWidth = 1.5;
    ctx.fill();
    ctx.stroke();
    ctx.restore();
  }

  function draw() {
    const { w, h } = size();
    const ratio = window.devicePixelRatio || 1;
    if (canvas.width !== Math.round(w * ratio)) {
      canvas.width = Math.round(w * ratio);
      canvas.height = Math.round(h * ratio);
    }
    ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
    ctx.clearRect(0, 0, w, h);
    const job = currentJob();
    const layer = job && (job.layer || job.previewLayer);
    if (layer) ctx.drawImage(layer, 0, 0, w, h);
    for (const stroke of app.strokes) {
      const points = ramped(stroke);
      path(points, { color: "#1d2733", width: 3 });
      directions(points, "#1d2733");
    }
    if (app.drawing) path(app.drawing, { color: "#1d2733", width: 3 });
    if (job && job.result && job.layer) {
      for (const r of job.result.reproductions) path(r, { color: "#e8710a", width: 2, dash: [6, 4] });
    }
    const ro = app.rollout;
    if (ro) {
      for (const piece of ro.trail) path(piece.points, { color: piece.push ? "#7d8896" : "#1f6feb", width: piece.push ? 2 : 3, dash: piece.push ? [4, 4] : [] });
      if (ro.position) {
        const [px, py] = toPixels(ro.position);
        ctx.beginPath();
        ctx.arc(px, py, 8, 0, 2 * Math.PI);
        ctx.fillStyle = ro.status === "arrived" ? "#1a7f37" : "#1f6feb";
        ctx.fill();
        ctx.strokeStyle = "#fff";
        ctx.lineWidth = 2;
        ctx.stroke();
      }
    }
    const goal = target();
    if (goal) star(toPixels(goal), 11);
    if (app.refining) {
      ctx.fillStyle = "rgba(31, 111, 235, 0.9)";
      ctx.font = "600 14px system-ui, sans-serif";
      ctx.fillText("Refining with the new stroke...", 12, 22);
    } else if (app.showBC && job) {
      ctx.fillStyle = "rgba(150, 40, 40, 0.85)";
      ctx.font = "600 14px system-ui, sans-serif";
      ctx.fillText(job.method === "bc" ? "BC: no stability guarantee" : "BC training; SNDS shown until it is done", 12, 22);
    }
  }

  // --- Rollouts -----------------------------------------------------------------------------

  let rolloutToken = 0;
  // Seconds of motion per rollout request: the page asks for the next piece while it plays
  // one, so the point moves at once and the server never computes what a push throws away.
  const CHUNK = 1.0;
  // Pieces are requested ahead until this many seconds of motion are ready to play.
  const AHEAD = 0.8;

  async function fetchChunk(ro, token) {
    const job = currentJob();
    ro.pending = true;
    let answer;
    try {
      // A model with a phase goes on with the phase it has (a new start would get another).
      const body = { start: ro.states[ro.states.length - 1], duration: CHUNK };
      if (ro.phases.length && ro.phases[ro.phases.length - 1]) body.phase = ro.phases[ro.phases.length - 1];
      answer = await api(`/api/jobs/${job.id}/rollout`, body);
    } catch (error) {
      if (token === rolloutToken) { ro.status = "stopped"; say(error.message, true); }
      return;
    }
    if (token !== rolloutToken) return;
    const offset = ro.t[ro.t.length - 1];
    if (ro.phases.length === 1 && ro.phases[0] === null) ro.phases[0] = answer.phases[0];
    for (let k = 1; k < answer.t.length; k++) {
      ro.t.push(offset + answer.t[k]);
      ro.states.push(answer.states[k]);
      ro.phases.push(answer.phases[k]);
    }
    ro.integrator = answer.integrator;
    ro.finalDistance = answer.final_distance;
    ro.tolerance = answer.tolerance;
    ro.arrived = answer.arrived;
    // Done when it arrived, or after the stability check's horizon (10 demonstration lengths).
    ro.complete = answer.arrived || ro.t[ro.t.length - 1] >= 10 * job.result.duration;
    ro.pending = false;
  }

  // A push keeps the phase the point had (phase: null lets the server give a new start its own).
  async function startRollout(start, trail = [], phase = null) {
    const job = currentJob();
    if (!job || !job.result) return;
    const token = ++rolloutToken;
    const piece = { points: [start], push: false };
    const ro = { status: "requesting", position: start, trail, start, t: [0], states: [start], phases: [phase], piece, index: 0 };
    app.rollout = ro;
    draw();
    await fetchChunk(ro, token);
    if (token !== rolloutToken || ro.status === "stopped") return;
    trail.push(piece);
    ro.status = "running";
    ro.clock = performance.now();
    requestAnimationFrame((now) => animate(now, token));
  }

  // Plays the rollout back at the speed of the strokes' own clock (real time).
  function animate(now, token) {
    const ro = app.rollout;
    if (!ro || token !== rolloutToken || ro.status !== "running") return;
    const { t, states } = ro;
    let tau = (now - ro.clock) / 1000;
    if (!ro.complete && !ro.pending && t[t.length - 1] - tau < AHEAD) fetchChunk(ro, token);
    if (!ro.complete && tau > t[t.length - 1]) {
      // The next piece is late: wait for it where the point is, without skipping ahead.
      ro.clock = now - 1000 * t[t.length - 1];
      tau = t[t.length - 1];
    }
    while (ro.index < t.length - 1 && t[ro.index + 1] <= tau) {
      ro.index += 1;
      ro.piece.points.push(states[ro.index]);
    }
    if (ro.complete && ro.index >= t.length - 1) {
      ro.position = states[states.length - 1];
      ro.status = ro.arrived ? "arrived" : "stopped";
      const seconds = t[t.length - 1].toFixed(2);
      const pushes = ro.trail.filter((piece) => piece.push).length;
      const after = pushes ? ` after ${pushes === 1 ? "a push" : `${pushes} pushes`}` : "";
      say(ro.arrived
        ? `Reached the target${after}, ${seconds} s from the last start.`
        : `Did not reach the target in ${seconds} s (${ro.integrator}).`, !ro.arrived);
    } else if (ro.index < t.length - 1) {
      const k = ro.index;
      const s = (tau - t[k]) / Math.max(1e-12, t[k + 1] - t[k]);
      ro.position = [0, 1].map((d) => states[k][d] + s * (states[k + 1][d] - states[k][d]));
    }
    draw();
    if (ro.status === "running") requestAnimationFrame((next) => animate(next, token));
  }

  // --- Pointer input: strokes, the target, clicks and pushes --------------------------------

  function setMode(mode) {
    app.mode = mode;
    $("mode-draw").classList.toggle("active", mode === "draw");
    $("mode-run").classList.toggle("active", mode === "run");
    canvas.style.cursor = mode === "draw" ? "crosshair" : "pointer";
  }

  canvas.addEventListener("pointerdown", (event) => {
    if (event.button !== 0) return;
    const p = eventWorld(event);
    try {
      canvas.setPointerCapture(event.pointerId);
    } catch (error) { /* a synthetic pointer has nothing to capture */ }
    const ro = app.rollout;
    if (app.mode === "run") {
      if (ro && ro.position && pixelDistance(p, ro.position) < 16) {
        app.dragging = "point";
        rolloutToken += 1; // stops the animation where it is
        ro.status = "pushed";
        ro.pushFrom = ro.position;
        ro.trail.push({ points: [ro.position], push: true });
      } else {
        startRollout(p);
      }
      return;
    }
    const goal = target();
    if (goal && pixelDistance(p, goal) < 14) {
      app.dragging = "target";
      return;
    }
    if (app.limits && app.strokes.length >= app.limits.max_strokes) {
      say(`At most ${app.limits.max_strokes} strokes: undo one first.`, true);
      return;
    }
    app.drawing = [[p[0], p[1], 0]];
    app.drawStart = event.timeStamp;
  });

  canvas.addEventListener("pointermove", (event) => {
    if (app.dragging === "target") {
      app.target = eventWorld(event);
      draw();
      return;
    }
    if (app.dragging === "point") {
      const ro = app.rollout;
      ro.position = eventWorld(event);
      ro.trail[ro.trail.length - 1].points.push(ro.position);
      draw();
      return;
    }
    if (!app.drawing) return;
    const events = event.getCoalescedEvents ? event.getCoalescedEvents() : [event];
    for (const e of events.length ? events : [event]) {
      const [x, y] = eventWorld(e);
      const t = (e.timeStamp - app.drawStart) / 1000;
      const last = app.drawing[app.drawing.length - 1];
      // Times must increase and points must differ, or the samples say nothing.
      if (t <= last[2] || Math.hypot(x - last[0], y - last[1]) < 0.2) continue;
      if (app.limits && app.drawing.length >= app.limits.max_points) break;
      app.drawing.push([x, y, t]);
    }
    draw();
  });

  function pointerUp() {
    if (app.dragging === "target") {
      app.dragging = null;
      strokesChanged();
      return;
    }
    if (app.dragging === "point") {
      app.dragging = null;
      const ro = app.rollout;
      const phase = ro.phases[Math.min(ro.index, ro.phases.length - 1)];
      startRollout(ro.position, ro.trail, phase && phase.length ? phase : null);
      return;
    }
    if (!app.drawing) return;
    const stroke = app.drawing;
    app.drawing = null;
    if (stroke.length < 2) {
      say("A stroke needs at least 2 points: drag while pressing.", true);
      draw();
      return;
    }
    addStroke(stroke);
  }

  // A finished stroke ([x, y, t] points): it refines the policy shown, if there is one.
  function addStroke(stroke) {
    app.strokes.push(stroke);
    const shown = app.jobs.snds;
    if (shown && shown.layer && !app.refining) {
      refine(shown);
      return;
    }
    say(`${app.strokes.length} stroke${app.strokes.length > 1 ? "s" : ""}. Draw more, or train.`);
    strokesChanged();
  }
  app.addStroke = addStroke;

  // --- Refinement: a stroke added after training ------------------------------------------

  async function refine(base) {
    if (stream) stream.close();
    app.history.push({ strokes: app.strokes.length - 1, jobs: { ...app.jobs }, drawn: { ...app.drawn } });
    // BC stays trained on the strokes before; it is dropped, and SNDS is shown.
    app.jobs.bc = null;
    app.drawn.bc = false;
    app.showBC = $("bc").checked = false;
    const job = { id: null, method: "snds", status: { state: "training" }, refines: base };
    app.refining = job;
    app.timings.refine = { added: performance.now() };
    document.body.dataset.state = "refining";
    jobProgress(job, 0, "SNDS: refining with the new stroke...");
    say("Refining the policy with the new stroke...");
    updateButtons();
    draw();
    try {
      job.status = await api(`/api/jobs/${base.id}/refine`, strokesBody());
    } catch (error) {
      if (app.refining !== job) return;
      app.refining = null;
      say(`Refining failed: ${error.message} (Undo removes the stroke)`, true);
      document.body.dataset.state = "trained";
      showProgress();
      updateButtons();
      draw();
      return;
    }
    job.id = job.status.id;
    if (app.refining !== job) {
      api(`/api/jobs/${job.id}`, undefined, { method: "DELETE" }).catch(() => {});
      return;
    }
    watch(job);
  }

  function cancelRefinement() {
    const job = app.refining;
    app.refining = null;
    if (job && job.id) api(`/api/jobs/${job.id}`, undefined, { method: "DELETE" }).catch(() => {});
  }

  // Undo of a stroke that refined the policy: the policy before it comes back.
  function undoRefinement() {
    const last = app.history.pop();
    if (stream) stream.close();
    stream = null;
    if (app.refining) cancelRefinement();
    app.strokes.pop();
    app.jobs = last.jobs;
    app.drawn = last.drawn;
    app.rollout = null;
    rolloutToken += 1;
    app.showBC = $("bc").checked = false;
    const job = app.jobs.snds;
    if (job && !["done", "error", "cancelled"].includes(job.status.state)) {
      job.progress = [1, "SNDS: trained (its check stopped for the refinement)"];
    }
    document.body.dataset.state = "trained";
    say("Undone: the policy before the stroke is back.");
    showProgress();
    showMetrics();
    updateButtons();
    draw();
  }
  canvas.addEventListener("pointerup", pointerUp);
  canvas.addEventListener("pointercancel", pointerUp);

  // --- Controls -----------------------------------------------------------------------------

  function updateButtons() {
    const busy = Object.values(app.jobs).some((job) => job && ["training", "checking"].includes(job.status.state));
    const snds = app.jobs.snds;
    const shown = currentJob();
    $("train").disabled = !app.strokes.length;
    $("train").title = busy ? "train again on the strokes as they are (cancels the running job)" : "train a stable policy on the strokes";
    $("undo").disabled = !app.strokes.length;
    $("clear").disabled = !app.strokes.length;
    $("mode-run").disabled = !(shown && shown.layer);
    $("bc").disabled = !(snds && snds.status.state === "done") && !app.showBC;
    $("dl-model").disabled = !(shown && shown.status.state === "done");
    $("dl-onnx").disabled = !(shown && shown.result);
    $("dl-strokes").disabled = !app.strokes.length;
  }

  function fmt(value, digits = 3) {
    if (value == null) return "–";
    if (value === 0) return "0";
    return Math.abs(value) >= 1e-3 && Math.abs(value) < 1e4 ? value.toPrecision(digits) : value.toExponential(digits - 1);
  }

  function showMetrics() {
    for (const method of ["snds", "bc"]) {
      const job = app.jobs[method];
      const m = job && job.status.metrics;
      const s = m && m.stability;
      const set = (name, text) => { $(`${method}-${name}`).textContent = text; };
      const arrived = s ? Math.round(s.converged_fraction * s.rollouts) : 0;
      set("converged", s ? `${arrived} of ${s.rollouts}` : "–");
      set("arrival", s && arrived ? `${fmt(s.time_to_arrive_median, 2)} s, ${fmt(s.time_to_arrive_median_durations, 2)}×` : "–");
      set("retrace", m && m.retrace_frechet_max != null ? `${fmt(100 * m.retrace_frechet_max, 2)} %` : "–");
      set("violations", s ? (s.samples_checked ? `${s.decrease_violations} of ${s.samples_checked}` : "no V") : "–");
      set("safe", s ? (s.largest_safe_dt == null ? "no V" : `${fmt(s.largest_safe_dt, 2)} s`) : "–");
      set("shortened", s ? (s.largest_safe_dt == null ? "no guard" : `${fmt(100 * s.shortened_fraction, 2)} %`) : "–");
      set("mse", m ? fmt(m.velocity_mse_paper) : "–");
      set("time", m && m.train_seconds != null ? `${m.train_seconds.toFixed(1)} s` : "–");
    }
    const shown = Object.values(app.jobs).find((job) => job && job.status.metrics);
    $("data-step").textContent = shown ? `data step ${fmt(shown.status.metrics.stability.dt, 2)} s; longest stroke ${fmt(shown.status.metrics.stability.duration, 2)} s` : "";
    const warnings = $("warnings");
    warnings.replaceChildren();
    for (const method of ["snds", "bc"]) {
      const m = app.jobs[method] && app.jobs[method].status.metrics;
      for (const text of (m && m.warnings) || []) {
        const item = document.createElement("li");
        item.textContent = `${method.toUpperCase()}: ${text}`;
        warnings.appendChild(item);
      }
    }
  }

  async function download(path, name, body) {
    say(`Preparing ${name}...`);
    try {
      const response = body === undefined
        ? await api(path, undefined, { method: "GET", raw: true })
        : await api(path, body, { raw: true });
      const blob = await response.blob();
      const link = document.createElement("a");
      link.href = URL.createObjectURL(blob);
      link.download = name;
      document.body.appendChild(link);
      link.click();
      link.remove();
      setTimeout(() => URL.revokeObjectURL(link.href), 10000);
      say(`Downloaded ${name}.`);
    } catch (error) {
      say(error.message, true);
    }
  }

  $("mode-draw").onclick = () => setMode("draw");
  $("mode-run").onclick = () => setMode("run");
  $("undo").onclick = () => {
    const last = app.history[app.history.length - 1];
    if (last && last.strokes === app.strokes.length - 1) {
      undoRefinement();
      return;
    }
    app.strokes.pop();
    if (!app.strokes.length) app.target = null;
    strokesChanged();
  };
  $("clear").onclick = () => { app.strokes = []; app.target = null; app.view = { ...DEFAULT_VIEW }; strokesChanged(); say("Cleared."); };
  $("train").onclick = () => { app.showBC = $("bc").checked = false; app.rollout = null; train("snds"); };
  $("bc").onchange = () => {
    app.showBC = $("bc").checked;
    app.rollout = null;
    rolloutToken += 1;
    const bc = app.jobs.bc;
    if (app.showBC && (!bc || ["error", "cancelled"].includes(bc.status.state))) train("bc");
    else showProgress();
    if (currentJob() && currentJob().layer) setMode(app.mode);
    updateButtons();
    draw();
  };
  $("dl-model").onclick = () => { const job = currentJob(); download(`/api/jobs/${job.id}/model.zip`, `snds-${job.method}-model.zip`); };
  $("dl-onnx").onclick = () => { const job = currentJob(); download(`/api/jobs/${job.id}/policy.onnx`, `snds-${job.method}-policy.onnx`); };
  $("dl-strokes").onclick = () => download("/api/strokes.csv", "strokes.csv", strokesBody());
  $("upload").onchange = async (event) => {
    const file = event.target.files[0];
    event.target.value = "";
    if (!file) return;
    try {
      const answer = await api("/api/strokes/upload", await file.text(), { type: "text/csv" });
      app.strokes = answer.strokes;
      app.target = answer.target;
      fitView();
      strokesChanged();
      say(`Opened ${file.name}: ${app.strokes.length} stroke(s). Train to continue.`);
    } catch (error) {
      say(error.message, true);
    }
  };

  // An opened file may be in any units: frame its strokes with a margin, at the board's 4:3.
  function fitView() {
    const points = app.strokes.flat().concat([target()]);
    const xs = points.map((p) => p[0]);
    const ys = points.map((p) => p[1]);
    const cx = (Math.min(...xs) + Math.max(...xs)) / 2;
    const cy = (Math.min(...ys) + Math.max(...ys)) / 2;
    const half = 0.65 * Math.max(Math.max(...xs) - Math.min(...xs), (4 / 3) * (Math.max(...ys) - Math.min(...ys)), 1e-9);
    app.view = { x0: cx - half, x1: cx + half, y0: cy - 0.75 * half, y1: cy + 0.75 * half };
  }

  window.addEventListener("resize", () => {
    for (const job of Object.values(app.jobs)) {
      if (job && job.field) job.layer = renderLayer(job);
      else if (job && job.preview) job.previewLayer = renderLayer(job, job.preview);
    }
    draw();
  });

  api("/api/limits", undefined, { method: "GET" }).then((limits) => { app.limits = limits; }).catch((error) => say(error.message, true));
  updateButtons();
  draw();
})();
