// The labeling page of `freipose label`: every view of one instant, labels saved on each edit.
// Server state per instant (GET/POST /api/instant/<i>): labels, predicted, points3d,
// projected, residuals, bones, progress, version; with several animals also individual,
// animals (the instants of the same frame, one per animal) and others (their labels).
// Image coordinates are pixels with the origin at the centre of the top-left pixel.
"use strict";

const FP = (() => {
  const S = {
    cfg: null, idx: 0, cur: null, labels: {}, kp: 0, active: null, views: {},
    undo: [], saving: false, pending: false, flushing: null, drag: null, pan: null,
    yaw: 0.6, pitch: 0.5, lastSwitchMs: null, depths: null, conflicts: 0,
  };
  const HIT = 9; // CSS px: grab radius of a marker
  // colours of the other animals' labels (drawn for reference, not editable)
  const ANIMAL_COLORS = ["#ffd166", "#06d6a0", "#ef476f", "#118ab2", "#f78c6b", "#c77dff"];
  function animalColor(name) {
    const a = (S.cfg.animals || []).indexOf(name);
    return ANIMAL_COLORS[(a < 0 ? 0 : a) % ANIMAL_COLORS.length];
  }

  async function api(path, opts) {
    const r = await fetch(path, Object.assign({ credentials: "same-origin" }, opts || {}));
    const body = await r.json().catch(() => ({}));
    return { status: r.status, body };
  }

  function camOf(name) { return S.cfg.cameras[S.cur.session + "/" + name]; }
  function kpName(k) { return S.cfg.keypoints[k]; }
  function label(cam, kp) { return (S.labels[cam] || {})[kp]; }

  // -- views ---------------------------------------------------------------------------
  function buildGrid(cams) {
    const grid = document.getElementById("grid");
    grid.innerHTML = "";
    const cols = Math.ceil(Math.sqrt(cams.length));
    grid.style.gridTemplateColumns = `repeat(${cols}, 1fr)`;
    grid.style.gridTemplateRows = `repeat(${Math.ceil(cams.length / cols)}, 1fr)`;
    S.views = {};
    for (const cam of cams) {
      const div = document.createElement("div");
      div.className = "view";
      div.dataset.camera = cam;
      const canvas = document.createElement("canvas");
      const tag = document.createElement("div");
      tag.className = "label";
      div.append(canvas, tag);
      grid.append(div);
      const v = { cam, div, canvas, tag, img: null, s: 1, tx: 0, ty: 0, fitted: false };
      S.views[cam] = v;
      attachMouse(v);
    }
    S.active = cams[0];
  }

  function fit(v) {
    const c = camOf(v.cam);
    const w = v.div.clientWidth, h = v.div.clientHeight;
    v.s = Math.min(w / c.size[0], h / c.size[1]);
    v.tx = (w - c.size[0] * v.s) / 2 + 0.5 * v.s;
    v.ty = (h - c.size[1] * v.s) / 2 + 0.5 * v.s;
    v.fitted = true;
  }

  function toImage(v, e) {
    const r = v.canvas.getBoundingClientRect();
    return [(e.clientX - r.left - v.tx) / v.s, (e.clientY - r.top - v.ty) / v.s];
  }

  function toScreen(v, p) { return [p[0] * v.s + v.tx, p[1] * v.s + v.ty]; }

  // Client (page) coordinates of image pixel (u, v) of a camera: for tests and tools.
  function imageToClient(cam, u, vv) {
    const v = S.views[cam];
    const r = v.canvas.getBoundingClientRect();
    const p = toScreen(v, [u, vv]);
    return [r.left + p[0], r.top + p[1]];
  }

  function setView(cam, scale, cu, cv) {
    const v = S.views[cam];
    v.s = scale;
    v.tx = v.div.clientWidth / 2 - cu * scale;
    v.ty = v.div.clientHeight / 2 - cv * scale;
    drawAll();
  }

  function inside(cam, p) {
    const c = camOf(cam);
    return p && p[0] >= -0.5 && p[1] >= -0.5 && p[0] <= c.size[0] - 0.5 && p[1] <= c.size[1] - 0.5;
  }

  // Where a keypoint is shown in a view: label, else projection, else prediction.
  function shown(cam, kp) {
    const l = label(cam, kp);
    if (l && l.state === "visible") return { p: [l.x, l.y], kind: "label" };
    if (l) return null;
    const live = liveProjection(cam, kp);
    if (live) return { p: live, kind: "projected" };
    const pr = (S.cur.projected[cam] || {})[kp];
    if (pr && S.cur.points3d[kp]) return { p: pr, kind: "projected" };
    const pd = (S.cur.predicted[cam] || {})[kp];
    if (pd && !anyLabel(kp)) return { p: pd, kind: "predicted" };
    return null;
  }

  // While a label is dragged: its keypoint triangulated in the page from the labels as
  // they are now, projected into `cam` (the server's triangulation follows on release).
  function liveProjection(cam, kp) {
    if (!S.drag || S.drag.kp !== kp) return null;
    if (!S.drag.live) {
      const cams = [], uvs = [];
      for (const c of S.cur.cameras) {
        const l = label(c, kp);
        if (l && l.state === "visible") { cams.push(camOf(c)); uvs.push([l.x, l.y]); }
      }
      const X = cams.length >= 2 ? FPGeom.triangulate(cams, uvs) : null;
      S.drag.live = { X };
    }
    return S.drag.live.X ? FPGeom.project(camOf(cam), S.drag.live.X) : null;
  }

  function anyLabel(kp) {
    return S.cur.cameras.some((c) => label(c, kp));
  }

  function epipolarDepths() {
    if (S.depths) return S.depths;
    const cs = Object.values(S.cfg.cameras).map(FPGeom.center);
    const mean = [0, 1, 2].map((i) => cs.reduce((a, c) => a + c[i], 0) / cs.length);
    const far = Math.max(...cs.map((c) => Math.hypot(c[0] - mean[0], c[1] - mean[1], c[2] - mean[2])));
    S.depths = FPGeom.depths(Math.max(far, 1) * 0.02, Math.max(far, 1) * 6, 400);
    return S.depths;
  }

  function drawCurve(ctx, v, pts, color) {
    ctx.strokeStyle = color;
    ctx.lineWidth = 1.5;
    ctx.setLineDash([6, 4]);
    ctx.beginPath();
    let on = false;
    const c = camOf(v.cam);
    const m = Math.max(c.size[0], c.size[1]);
    for (const p of pts) {
      const ok = p && p[0] > -m && p[1] > -m && p[0] < 2 * m && p[1] < 2 * m;
      if (!ok) { on = false; continue; }
      const q = toScreen(v, p);
      if (on) ctx.lineTo(q[0], q[1]); else ctx.moveTo(q[0], q[1]);
      on = true;
    }
    ctx.stroke();
    ctx.setLineDash([]);
  }

  // a limb's two ends in image pixels (each end the mean of its keypoints), null unless
  // every keypoint has a point: pointOf(k) gives keypoint k's [x, y] or nothing
  function limbEnds(limb, pointOf) {
    const ends = limb.map((ix) => {
      const ps = ix.map(pointOf);
      if (ps.some((p) => !p)) return null;
      return [0, 1].map((d) => ps.reduce((s, p) => s + p[d], 0) / ps.length);
    });
    return ends[0] && ends[1] ? ends : null;
  }

  function drawView(v) {
    const canvas = v.canvas, dpr = window.devicePixelRatio || 1;
    const w = v.div.clientWidth, h = v.div.clientHeight;
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr);
      canvas.height = Math.round(h * dpr);
    }
    if (!v.fitted) fit(v);
    const ctx = canvas.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = "#000";
    ctx.fillRect(0, 0, w, h);
    const c = camOf(v.cam);
    if (v.img && v.img.complete && v.img.naturalWidth) {
      ctx.imageSmoothingEnabled = v.s < 2;
      ctx.drawImage(v.img, v.tx - 0.5 * v.s, v.ty - 0.5 * v.s, c.size[0] * v.s, c.size[1] * v.s);
    }
    const kps = S.cfg.keypoints;
    // skeleton
    ctx.lineWidth = 1.5;
    for (const limb of S.cfg.limbs) {
      const ends = limbEnds(limb, (k) => { const sh = shown(v.cam, kps[k]); return sh && sh.p; });
      if (!ends) continue;
      const p = toScreen(v, ends[0]), q = toScreen(v, ends[1]);
      ctx.strokeStyle = "rgba(255,255,255,0.55)";
      ctx.beginPath(); ctx.moveTo(p[0], p[1]); ctx.lineTo(q[0], q[1]); ctx.stroke();
    }
    // the other animals of this frame: their labels as small squares and thin limbs
    for (const [name, views] of Object.entries(S.cur.others || {})) {
      const pts = views[v.cam] || {};
      const col = animalColor(name);
      ctx.strokeStyle = col;
      ctx.lineWidth = 1;
      ctx.setLineDash([3, 3]);
      for (const limb of S.cfg.limbs) {
        const ends = limbEnds(limb, (k) => pts[kps[k]]);
        if (!ends) continue;
        const p = toScreen(v, ends[0]), q = toScreen(v, ends[1]);
        ctx.beginPath(); ctx.moveTo(p[0], p[1]); ctx.lineTo(q[0], q[1]); ctx.stroke();
      }
      ctx.setLineDash([]);
      let first = null;
      for (const p of Object.values(pts)) {
        const q = toScreen(v, p);
        ctx.strokeRect(q[0] - 3, q[1] - 3, 6, 6);
        if (!first || q[1] < first[1]) first = q;
      }
      if (first) {
        ctx.fillStyle = col;
        ctx.font = "11px sans-serif";
        ctx.fillText(name, first[0] + 6, first[1] - 6);
      }
    }
    // epipolar curves of the current keypoint from the other views' labels
    const kp = kpName(S.kp);
    for (const other of S.cur.cameras) {
      if (other === v.cam) continue;
      const l = label(other, kp);
      if (!l || l.state !== "visible") continue;
      const pts = FPGeom.epipolar(camOf(other), l.x, l.y, c, epipolarDepths());
      drawCurve(ctx, v, pts, S.cfg.colors[S.kp]);
    }
    // markers
    kps.forEach((name, k) => {
      const sh = shown(v.cam, name);
      if (!sh) return;
      const q = toScreen(v, sh.p);
      const cur = k === S.kp;
      const r = cur ? 6 : 4;
      ctx.strokeStyle = S.cfg.colors[k];
      ctx.fillStyle = S.cfg.colors[k];
      ctx.lineWidth = cur ? 2.5 : 1.5;
      ctx.beginPath();
      ctx.arc(q[0], q[1], r, 0, 2 * Math.PI);
      if (sh.kind === "label") {
        ctx.fill();
        if (cur) { ctx.strokeStyle = "#fff"; ctx.stroke(); }
      } else {
        if (sh.kind === "predicted") ctx.setLineDash([2, 2]);
        ctx.stroke();
        ctx.setLineDash([]);
      }
      const res = (S.cur.residuals[v.cam] || {})[name];
      if (sh.kind === "label" && res !== undefined && res > S.cfg.max_residual) {
        ctx.strokeStyle = "#ff3030";
        ctx.lineWidth = 2;
        ctx.beginPath(); ctx.arc(q[0], q[1], r + 4, 0, 2 * Math.PI); ctx.stroke();
        ctx.fillStyle = "#ff5050";
        ctx.font = "11px sans-serif";
        ctx.fillText(res.toFixed(1) + " px", q[0] + r + 5, q[1] - r);
      }
    });
    const l = label(v.cam, kp);
    const st = l ? l.state : (shown(v.cam, kp) || { kind: "unlabeled" }).kind;
    v.tag.textContent = `${v.cam} · ${kp}: ${st}`;
    v.div.classList.toggle("active", v.cam === S.active);
  }

  function drawAll() {
    if (!S.cur) return;
    for (const v of Object.values(S.views)) drawView(v);
    draw3d();
  }

  // -- 3D view -------------------------------------------------------------------------
  function draw3d() {
    const canvas = document.getElementById("view3d");
    const ctx = canvas.getContext("2d");
    ctx.fillStyle = "#111";
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    const pts = S.cur.points3d, names = Object.keys(pts);
    if (!names.length) {
      ctx.fillStyle = "#777";
      ctx.fillText("3D: label a keypoint in two views", 10, 20);
      return;
    }
    const mean = [0, 1, 2].map((i) => names.reduce((a, n) => a + pts[n][i], 0) / names.length);
    const cy = Math.cos(S.yaw), sy = Math.sin(S.yaw), cp = Math.cos(S.pitch), sp = Math.sin(S.pitch);
    const proj = (X) => {
      const x = X[0] - mean[0], y = X[1] - mean[1], z = X[2] - mean[2];
      const xr = cy * x - sy * y, yr = sy * x + cy * y;
      return [xr, -(cp * z - sp * yr)];
    };
    const flat = names.map((n) => proj(pts[n]));
    const ext = Math.max(20, ...flat.map((p) => Math.max(Math.abs(p[0]), Math.abs(p[1]))));
    const sc = (Math.min(canvas.width, canvas.height) / 2 - 12) / ext;
    const at = (X) => { const p = proj(X); return [canvas.width / 2 + p[0] * sc, canvas.height / 2 + p[1] * sc]; };
    const kps = S.cfg.keypoints;
    ctx.strokeStyle = "#aaa";
    for (const [a, b] of S.cfg.limbs) {
      const ends = [a, b].map((ix) => {
        if (ix.some((k) => !pts[kps[k]])) return null;
        return [0, 1, 2].map((d) => ix.reduce((s, k) => s + pts[kps[k]][d], 0) / ix.length);
      });
      if (!ends[0] || !ends[1]) continue;
      const p = at(ends[0]), q = at(ends[1]);
      ctx.beginPath(); ctx.moveTo(p[0], p[1]); ctx.lineTo(q[0], q[1]); ctx.stroke();
    }
    kps.forEach((n, k) => {
      if (!pts[n]) return;
      const p = at(pts[n]);
      ctx.fillStyle = S.cfg.colors[k];
      ctx.beginPath(); ctx.arc(p[0], p[1], k === S.kp ? 5 : 3.5, 0, 2 * Math.PI); ctx.fill();
    });
  }

  // -- side panel ----------------------------------------------------------------------
  function renderSide() {
    const box = document.getElementById("keypoints");
    box.innerHTML = "";
    S.cfg.keypoints.forEach((name, k) => {
      const row = document.createElement("div");
      row.className = "kp" + (k === S.kp ? " current" : "");
      row.dataset.k = k;
      const n = S.cur.cameras.filter((c) => label(c, name) && label(c, name).state === "visible").length;
      const marks = S.cur.cameras.filter((c) => label(c, name) && label(c, name).state !== "visible").length;
      const res = S.cur.cameras.map((c) => (S.cur.residuals[c] || {})[name]).filter((r) => r !== undefined);
      const worst = res.length ? Math.max(...res) : null;
      const bad = worst !== null && worst > S.cfg.max_residual;
      row.innerHTML = `<span class="sw" style="background:${S.cfg.colors[k]}"></span>` +
        `<span class="n">${name}</span><span class="info">${n}/${S.cur.cameras.length}` +
        (marks ? ` +${marks} marked` : "") + (S.cur.points3d[name] ? " 3D" : "") +
        (worst !== null ? ` <span class="${bad ? "bad" : ""}">${worst.toFixed(1)}px</span>` : "") +
        "</span>";
      row.onclick = () => { S.kp = k; renderSide(); drawAll(); };
      box.append(row);
    });
    const bones = document.getElementById("bones");
    const flagged = S.cur.bones.filter((b) => b.flag);
    bones.innerHTML = "<b>Bone lengths</b> " + (S.cur.bones.length ? "" : "(none known yet)") +
      S.cur.bones.map((b) => {
        const [a, c] = S.cfg.limbs[b.limb];
        const nm = (ix) => ix.map((k) => S.cfg.keypoints[k]).join("+");
        const med = b.median === null ? "" : ` (median ${b.median.toFixed(0)})`;
        return `<div class="${b.flag ? "flag" : ""}">${nm(a)}–${nm(c)}: ${b.length.toFixed(0)} mm${med}</div>`;
      }).join("");
    bones.dataset.flagged = flagged.length;
    const p = S.cur.progress;
    document.getElementById("progress").textContent = `${p.labeled}/${p.total} instants labeled`;
    document.getElementById("kp-progress").innerHTML = "<b>Labeled instants per keypoint</b>" +
      S.cfg.keypoints.map((n, k) =>
        `<div class="row"><span style="width:120px">${n}</span><span class="bar"><div style="width:${
          (100 * p.per_keypoint[k]) / Math.max(1, p.total)}%"></div></span>${p.per_keypoint[k]}</div>`
      ).join("");
    const x = S.cfg.instants[S.idx];
    document.getElementById("where").textContent =
      `instant ${S.idx + 1}/${S.cfg.instants.length}: ${x.session} frame ${x.frame}` +
      (x.individual ? `, ${x.individual}` : "") +
      (x.confidence === null ? "" : ` (confidence ${x.confidence.toFixed(2)})`);
    renderAnimals();
  }

  // the animal selector: one button per animal of this frame (A: the next one)
  function renderAnimals() {
    const box = document.getElementById("animals");
    box.innerHTML = "";
    const list = S.cur.animals || [];
    box.hidden = list.length < 2;
    for (const a of list) {
      const b = document.createElement("button");
      b.textContent = a.name + (a.labeled ? " \u2713" : "");
      b.className = "animal" + (a.index === S.idx ? " current" : "");
      b.style.borderColor = animalColor(a.name);
      b.dataset.animal = a.name;
      b.title = `label ${a.name} at this instant (A: next animal)`;
      b.onclick = () => load(a.index);
      box.append(b);
    }
  }

  function nextAnimal() {
    const list = S.cur.animals || [];
    if (list.length < 2) return;
    const at = list.findIndex((a) => a.index === S.idx);
    load(list[(at + 1) % list.length].index);
  }

  // -- editing -------------------------------------------------------------------------
  function snapshot() { return JSON.stringify(S.labels); }

  function edit(fn) {
    S.undo.push(snapshot());
    fn();
    renderSide();
    drawAll();
    save();
  }

  function setLabel(cam, kp, entry) {
    if (!S.labels[cam]) S.labels[cam] = {};
    if (entry) S.labels[cam][kp] = entry; else delete S.labels[cam][kp];
  }

  function save() {
    S.pending = true;
    if (!S.saving) S.flushing = flush();
  }

  async function flush() {
    S.saving = true;
    const marker = document.getElementById("saved");
    while (S.pending) {
      S.pending = false;
      const idx = S.idx;
      const r = await api(`api/instant/${idx}`, {
        method: "POST",
        headers: { "Content-Type": "application/json" },
        body: JSON.stringify({ version: S.cur.version, labels: S.labels }),
      });
      if (r.status === 200) {
        applyState(r.body, false);
        marker.textContent = "saved";
        marker.className = "";
      } else if (r.status === 409) {
        S.conflicts += 1;
        S.pending = false;
        showBanner("This instant was changed in another tab or window; it was reloaded with " +
          "that version (your last edit was not saved).");
        applyState(r.body.current, true);
      } else {
        marker.textContent = "not saved: " + ((r.body && r.body.error) || r.status);
        marker.className = "error";
        if (r.body && r.body.write_error) showBanner(r.body.error, true);
      }
    }
    S.saving = false;
  }

  function showBanner(text, keep) {
    const b = document.getElementById("banner");
    b.textContent = text;
    b.hidden = false;
    if (!keep) setTimeout(() => { b.hidden = true; }, 8000);
  }

  function applyState(state, replaceLabels) {
    S.cur = state;
    if (replaceLabels) S.labels = JSON.parse(JSON.stringify(state.labels));
    renderSide();
    drawAll();
  }

  function acceptProjected(all) {
    const names = all ? S.cfg.keypoints : [kpName(S.kp)];
    edit(() => {
      for (const kp of names) {
        const todo = S.cur.cameras.map((cam) => [cam, shown(cam, kp)]); // before any change
        for (const [cam, sh] of todo) {
          if (sh && sh.kind !== "label" && !label(cam, kp) && inside(cam, sh.p)) {
            setLabel(cam, kp, { state: "visible", x: +sh.p[0].toFixed(3), y: +sh.p[1].toFixed(3) });
          }
        }
      }
    });
  }

  function mark(state) {
    const kp = kpName(S.kp), cam = S.active;
    edit(() => setLabel(cam, kp, state ? { state } : null));
  }

  function undo() {
    if (!S.undo.length) return;
    S.labels = JSON.parse(S.undo.pop());
    renderSide();
    drawAll();
    save();
  }

  // -- mouse ---------------------------------------------------------------------------
  function attachMouse(v) {
    v.canvas.addEventListener("contextmenu", (e) => e.preventDefault());
    v.canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      const r = v.canvas.getBoundingClientRect();
      const mx = e.clientX - r.left, my = e.clientY - r.top;
      const f = Math.exp(-e.deltaY * 0.0015);
      v.tx = mx - (mx - v.tx) * f;
      v.ty = my - (my - v.ty) * f;
      v.s *= f;
      drawView(v);
    }, { passive: false });
    v.canvas.addEventListener("mousedown", (e) => {
      S.active = v.cam;
      if (e.button === 1 || (e.button === 0 && e.shiftKey)) {
        S.pan = { v, x: e.clientX, y: e.clientY };
        e.preventDefault();
        return;
      }
      if (e.button !== 0) return;
      const p = toImage(v, e);
      if (!inside(v.cam, p)) return;
      const kp = kpName(S.kp);
      const before = snapshot();
      const sh = shown(v.cam, kp);
      let off = [0, 0];
      if (sh) {
        const q = toScreen(v, sh.p), m = toScreen(v, p);
        if (Math.hypot(q[0] - m[0], q[1] - m[1]) <= HIT) off = [sh.p[0] - p[0], sh.p[1] - p[1]];
      }
      S.drag = { v, kp, off, before };
      setLabel(v.cam, kp, { state: "visible", x: p[0] + off[0], y: p[1] + off[1] });
      drawAll();
      e.preventDefault();
    });
  }

  window.addEventListener("mousemove", (e) => {
    if (S.pan) {
      S.pan.v.tx += e.clientX - S.pan.x;
      S.pan.v.ty += e.clientY - S.pan.y;
      S.pan.x = e.clientX; S.pan.y = e.clientY;
      drawView(S.pan.v);
      return;
    }
    if (!S.drag) return;
    const v = S.drag.v, c = camOf(v.cam);
    const p = toImage(v, e);
    const x = Math.min(Math.max(p[0] + S.drag.off[0], -0.5), c.size[0] - 0.5);
    const y = Math.min(Math.max(p[1] + S.drag.off[1], -0.5), c.size[1] - 0.5);
    setLabel(v.cam, S.drag.kp, { state: "visible", x, y });
    S.drag.live = null;
    drawAll(); // the epipolar curves and projections in the other views follow the drag
  });

  window.addEventListener("mouseup", () => {
    if (S.pan) { S.pan = null; return; }
    if (!S.drag) return;
    const d = S.drag;
    S.drag = null;
    const l = label(d.v.cam, d.kp);
    setLabel(d.v.cam, d.kp, { state: "visible", x: +l.x.toFixed(3), y: +l.y.toFixed(3) });
    S.undo.push(d.before);
    renderSide();
    drawAll();
    save();
  });

  // -- navigation ----------------------------------------------------------------------
  // The query names the session and frame, so that a cached image never stands for
  // another frame after a restart with other instants.
  function frameUrl(i, cam) {
    const x = S.cfg.instants[i];
    return `api/frame/${i}/${encodeURIComponent(cam)}?at=${encodeURIComponent(x.session + ":" + x.frame)}`;
  }

  async function load(i) {
    if (S.saving) await S.flushing; // the edits of this instant are saved before leaving it
    const t0 = performance.now();
    const n = S.cfg.instants.length;
    i = Math.max(0, Math.min(n - 1, i));
    S.idx = i;
    const r = await api(`api/instant/${i}`);
    if (i !== S.idx) return;
    const first = !S.cur || S.cur.cameras.join() !== r.body.cameras.join();
    S.cur = r.body;
    S.labels = JSON.parse(JSON.stringify(r.body.labels));
    S.undo = [];
    if (first) buildGrid(r.body.cameras);
    await Promise.all(r.body.cameras.map((cam) => new Promise((resolve) => {
      const img = new Image();
      img.onload = img.onerror = resolve;
      img.src = frameUrl(i, cam);
      S.views[cam].img = img;
    })));
    if (i !== S.idx) return;
    renderSide();
    drawAll();
    S.lastSwitchMs = performance.now() - t0;
    document.body.dataset.instant = String(i);
    for (const j of [i + 1, i + 2]) {
      if (j < n) r.body.cameras.forEach((cam) => { new Image().src = frameUrl(j, cam); });
    }
  }

  function leastConfident() {
    const done = S.cur.progress.done;
    let best = null;
    S.cfg.instants.forEach((x, j) => {
      if (done[j] || j === S.idx) return;
      const c = x.confidence === null ? 2 : x.confidence;
      if (best === null || c < best[0]) best = [c, j];
    });
    if (best !== null) load(best[1]);
  }

  function nextView(step) {
    const cams = S.cur.cameras;
    S.active = cams[(cams.indexOf(S.active) + step + cams.length) % cams.length];
    drawAll();
  }

  function selectKeypoint(step) {
    const K = S.cfg.keypoints.length;
    S.kp = (S.kp + step + K) % K;
    renderSide();
    drawAll();
  }

  window.addEventListener("keydown", (e) => {
    if (!S.cur) return;
    const k = e.key;
    if ((k === "z" || k === "Z") && !e.shiftKey) { undo(); e.preventDefault(); return; }
    if (e.ctrlKey || e.metaKey || e.altKey) return;
    const keys = {
      ArrowRight: () => load(S.idx + 1), ArrowLeft: () => load(S.idx - 1),
      ArrowDown: () => selectKeypoint(1), ArrowUp: () => selectKeypoint(-1),
      s: () => selectKeypoint(1), w: () => selectKeypoint(-1),
      l: () => leastConfident(), Tab: () => nextView(e.shiftKey ? -1 : 1), a: () => nextAnimal(),
      Enter: () => acceptProjected(e.shiftKey), o: () => mark("occluded"),
      x: () => mark("notinview"), Delete: () => mark(null), Backspace: () => mark(null),
      f: () => { Object.values(S.views).forEach(fit); drawAll(); },
      "?": () => { const h = document.getElementById("help"); h.hidden = !h.hidden; },
    };
    const fn = keys[k] || keys[k.toLowerCase()];
    if (fn) { fn(); e.preventDefault(); }
  });

  function attach3d() {
    const c = document.getElementById("view3d");
    let last = null;
    c.addEventListener("mousedown", (e) => { last = [e.clientX, e.clientY]; });
    window.addEventListener("mouseup", () => { last = null; });
    window.addEventListener("mousemove", (e) => {
      if (!last) return;
      S.yaw += (e.clientX - last[0]) * 0.01;
      S.pitch = Math.max(-1.5, Math.min(1.5, S.pitch + (e.clientY - last[1]) * 0.01));
      last = [e.clientX, e.clientY];
      draw3d();
    });
  }

  async function start() {
    const r = await api("api/config");
    S.cfg = r.body;
    document.getElementById("prev").onclick = () => load(S.idx - 1);
    document.getElementById("next").onclick = () => load(S.idx + 1);
    document.getElementById("least").onclick = leastConfident;
    document.getElementById("accept").onclick = () => acceptProjected(false);
    document.getElementById("undo").onclick = undo;
    document.getElementById("help-button").onclick = () => {
      const h = document.getElementById("help"); h.hidden = !h.hidden;
    };
    attach3d();
    window.addEventListener("resize", () => { Object.values(S.views).forEach(fit); drawAll(); });
    const done = await api("api/progress");
    const first = done.body.done.indexOf(false);
    await load(first < 0 ? 0 : first);
  }

  window.addEventListener("load", start);
  return { S, load, setView, imageToClient, acceptProjected, selectKeypoint, shown, nextAnimal };
})();
