"""The inline style and script of ``report.html`` (kept as Python strings so the package needs no
data files). The script reads the JSON in ``#run-data`` and draws on canvases; no library, no fetch."""

STYLE = r"""
:root { --ink:#1d2330; --muted:#5d6677; --line:#d9dee7; --bg:#f6f7f9; --card:#fff; --accent:#f08c00; }
* { box-sizing: border-box; }
body { margin:0; font:14px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; color:var(--ink); background:var(--bg); }
header { padding:20px 28px 8px; background:#1d2330; color:#fff; }
header h1 { margin:0; font-size:22px; font-weight:600; }
header .sub { margin:4px 0 14px; color:#b8c0cf; }
.figs { display:flex; flex-wrap:wrap; gap:10px; padding-bottom:14px; }
.fig { background:#2a3244; border-radius:8px; padding:8px 14px; min-width:110px; }
.fig .v { font-size:20px; font-weight:600; } .fig .v small { font-size:12px; margin-left:3px; color:#b8c0cf; }
.fig .k { font-size:12px; color:#b8c0cf; }
.notes { margin:0 0 12px; color:#ffd8a8; }
main { padding:8px 28px 40px; max-width:1400px; }
section { background:var(--card); border:1px solid var(--line); border-radius:10px; padding:14px 18px; margin:16px 0; }
h2 { margin:0 0 10px; font-size:16px; }
.toolbar { display:flex; flex-wrap:wrap; gap:14px; margin-bottom:8px; }
.toolbar label { display:flex; align-items:center; gap:6px; cursor:pointer; user-select:none; }
.swatch { display:inline-block; width:18px; height:4px; border-radius:2px; }
.view { position:relative; }
#topview { width:100%; height:620px; display:block; background:#10141c; border-radius:8px; cursor:grab; }
#topview.dragging { cursor:grabbing; }
.readout { position:absolute; right:10px; bottom:8px; color:#cfd6e4; font:12px ui-monospace, monospace; pointer-events:none; }
.player { display:flex; align-items:center; gap:10px; margin-top:10px; }
.player input { flex:1; } .player button { min-width:64px; padding:4px 10px; }
#now { font:12px ui-monospace, monospace; min-width:330px; color:var(--muted); }
.hint { color:var(--muted); margin:6px 0 0; font-size:12px; }
.chart { width:100%; height:220px; display:block; margin-top:6px; }
.metrics { columns:3 340px; column-gap:28px; font-size:13px; }
.metrics .row { display:flex; gap:10px; break-inside:avoid; padding:2px 0; border-bottom:1px solid #eef0f4; }
.metrics .k { color:var(--muted); flex:0 0 48%; overflow-wrap:anywhere; }
.metrics .v { font-family:ui-monospace, monospace; overflow-wrap:anywhere; }
.plots { display:flex; flex-wrap:wrap; gap:14px; }
figure { margin:0; flex:1 1 420px; } figure img { max-width:100%; border:1px solid var(--line); border-radius:6px; }
figcaption { color:var(--muted); font-size:12px; }
pre { background:#f1f3f6; padding:12px; border-radius:6px; overflow:auto; max-height:520px; font-size:12px; }
"""

SCRIPT = r"""
(function () {
  "use strict";
  var D = JSON.parse(document.getElementById("run-data").textContent);

  function bytes(b64) {
    var s = atob(b64 || ""), u = new Uint8Array(s.length);
    for (var i = 0; i < s.length; i++) u[i] = s.charCodeAt(i);
    return u.buffer;
  }
  function f64(b64) { return new Float64Array(bytes(b64)); }
  function f32(b64) { return new Float32Array(bytes(b64)); }

  var est = f64(D.est_xy), estT = f64(D.est_t), estYaw = f32(D.est_yaw);
  var gt = f64(D.gt_xy), gtT = f64(D.gt_t), mapXY = f32(D.map_xy);
  var F = D.frames, frameT = f64(F.t), nFrames = frameT.length;
  var series = {};
  Object.keys(F.series).forEach(function (k) { series[k] = f32(F.series[k].values); });
  var BAD = { 2: "#ff6b6b", 3: "#ff922b", 4: "#e03131", 5: "#868e96" };

  // ------------------------------------------------------------ shared state
  var state = { frame: nFrames ? nFrames - 1 : 0, playing: null,
                layers: { map: true, blocks: true, labels: true, gt: true, est: true, bad: true, robot: true } };
  var LAYERS = [["map", "map points", "#7f8da3"], ["blocks", "block outlines", "#4dabf7"],
                ["labels", "block names", "#adb5bd"], ["gt", "ground truth (dashed)", "#868e96"],
                ["est", "estimate", "#ffd43b"], ["bad", "not-ok frames", "#ff6b6b"], ["robot", "robot", "#f08c00"]];
  if (!gt.length) delete state.layers.gt;

  function lowerBound(arr, x) {
    var lo = 0, hi = arr.length;
    while (lo < hi) { var mid = (lo + hi) >> 1; if (arr[mid] < x) lo = mid + 1; else hi = mid; }
    return lo;
  }
  function estAt(t) {  // index of the estimate nearest to time t (or -1)
    if (!estT.length) return -1;
    var i = Math.min(lowerBound(estT, t), estT.length - 1);
    if (i > 0 && Math.abs(estT[i - 1] - t) < Math.abs(estT[i] - t)) i -= 1;
    return i;
  }

  function gtAt(t) {
    if (!gtT.length) return -1;
    return Math.min(lowerBound(gtT, t), gtT.length - 1);
  }
  function whereAt(t) {  // [x, y] of the robot at t: the estimate, or ground truth where none is near
    var i = estAt(t);
    if (i >= 0 && Math.abs(estT[i] - t) < 0.15) return [est[2 * i], est[2 * i + 1]];
    var g = gtAt(t);
    if (g >= 0) return [gt[2 * g], gt[2 * g + 1]];
    return i >= 0 ? [est[2 * i], est[2 * i + 1]] : null;
  }

  // ------------------------------------------------------------ the top view
  var cv = document.getElementById("topview"), ctx = cv.getContext("2d");
  var view = { scale: 1, cx: 0, cy: 0 }, W = 0, H = 0, dpr = window.devicePixelRatio || 1;

  function bounds() {
    var b = [Infinity, Infinity, -Infinity, -Infinity];
    function add(a, step) { for (var i = 0; i < a.length; i += step) {
      var x = a[i], y = a[i + 1]; if (x < b[0]) b[0] = x; if (y < b[1]) b[1] = y; if (x > b[2]) b[2] = x; if (y > b[3]) b[3] = y; } }
    add(est, 2); add(gt, 2);
    D.entries.forEach(function (e) { e.outline.forEach(function (p) { add(p, 2); }); });
    if (!isFinite(b[0])) add(mapXY, 2 * Math.max(1, Math.floor(mapXY.length / 20000)));
    if (!isFinite(b[0])) b = [-10, -10, 10, 10];
    return b;
  }
  function fit() {
    var b = bounds(), w = Math.max(b[2] - b[0], 1), h = Math.max(b[3] - b[1], 1);
    view.scale = 0.92 * Math.min(W / w, H / h);
    view.cx = (b[0] + b[2]) / 2; view.cy = (b[1] + b[3]) / 2;
  }
  function sx(x) { return (x - view.cx) * view.scale + W / 2; }
  function sy(y) { return H / 2 - (y - view.cy) * view.scale; }
  function resize() {
    var r = cv.getBoundingClientRect();
    W = Math.max(1, Math.round(r.width)); H = Math.max(1, Math.round(r.height));
    cv.width = Math.round(W * dpr); cv.height = Math.round(H * dpr);
  }

  function activeAt(frame) {
    var a = {};
    if (!nFrames) return a;
    var list = F.active[frame];
    if (list) list.forEach(function (id) { a[id] = true; });
    else if (F.block[frame] !== null) a[F.block[frame]] = true;
    return a;
  }

  function drawMap() {
    var img = ctx.createImageData(cv.width, cv.height), px = img.data, n = mapXY.length / 2, drawn = 0;
    for (var i = 0; i < n; i++) {
      var X = Math.round(sx(mapXY[2 * i]) * dpr), Y = Math.round(sy(mapXY[2 * i + 1]) * dpr);
      if (X < 0 || Y < 0 || X >= cv.width || Y >= cv.height) continue;
      var k = 4 * (Y * cv.width + X);
      px[k] = Math.min(255, px[k] + 85); px[k + 1] = Math.min(255, px[k + 1] + 100); px[k + 2] = Math.min(255, px[k + 2] + 125);
      px[k + 3] = 255; drawn++;
    }
    ctx.putImageData(img, 0, 0);
    return drawn;
  }
  function polyline(a, color, width, dash, gapT) {
    ctx.strokeStyle = color; ctx.lineWidth = width; ctx.setLineDash(dash || []);
    ctx.beginPath();
    for (var i = 0; i < a.length / 2; i++) {
      var x = sx(a[2 * i]), y = sy(a[2 * i + 1]);
      if (i === 0 || (gapT && gapT[i] - gapT[i - 1] > 1.0)) ctx.moveTo(x, y); else ctx.lineTo(x, y);
    }
    ctx.stroke(); ctx.setLineDash([]);
  }
  function drawTop() {
    var L = state.layers, stats = { map: 0, entries: 0, bad: 0, labels: 0 };
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.fillStyle = "#10141c"; ctx.fillRect(0, 0, cv.width, cv.height);
    if (L.map) stats.map = drawMap();
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    var active = activeAt(state.frame);
    if (L.blocks) {
      D.entries.forEach(function (e) {
        var on = !!active[e.id];
        ctx.strokeStyle = on ? "#f08c00" : "rgba(77,171,247,0.75)"; ctx.lineWidth = on ? 3 : 1.2;
        ctx.fillStyle = on ? "rgba(240,140,0,0.10)" : "rgba(77,171,247,0.03)";
        ctx.beginPath();
        e.outline.forEach(function (p, j) { if (j === 0) ctx.moveTo(sx(p[0]), sy(p[1])); else ctx.lineTo(sx(p[0]), sy(p[1])); });
        ctx.closePath(); ctx.fill(); ctx.stroke(); stats.entries++;
      });
    }
    if (L.labels && view.scale * 40 > 30) {
      ctx.font = "600 13px system-ui, sans-serif"; ctx.textAlign = "center"; ctx.lineJoin = "round";
      D.entries.forEach(function (e) {  // a dark halo keeps the name readable over dense points
        var x = sx(e.centroid[0]), y = sy(e.centroid[1]);
        ctx.strokeStyle = "rgba(16,20,28,0.9)"; ctx.lineWidth = 4; ctx.strokeText(e.id, x, y);
        ctx.fillStyle = active[e.id] ? "#ffc078" : "#a5d8ff"; ctx.fillText(e.id, x, y);
        stats.labels++;
      });
    }
    if (L.gt && gt.length) polyline(gt, "rgba(233,236,239,0.85)", 1.5, [6, 4]);
    if (L.est && est.length) polyline(est, "#ffd43b", 2.2, null, estT);
    if (L.bad) {
      for (var f = 0; f < nFrames; f++) {
        var code = F.status[f]; if (!BAD[code]) continue;
        var p = whereAt(frameT[f]); if (!p) continue;
        ctx.fillStyle = BAD[code]; ctx.beginPath();
        ctx.arc(sx(p[0]), sy(p[1]), 4, 0, 2 * Math.PI); ctx.fill(); stats.bad++;
      }
    }
    if (L.robot && nFrames && est.length) {
      var r = estAt(frameT[state.frame]), x = sx(est[2 * r]), y = sy(est[2 * r + 1]), a = -estYaw[r];
      ctx.save(); ctx.translate(x, y); ctx.rotate(a);
      ctx.fillStyle = "#f08c00"; ctx.strokeStyle = "#fff"; ctx.lineWidth = 1.5;
      ctx.beginPath(); ctx.moveTo(14, 0); ctx.lineTo(-9, 8); ctx.lineTo(-5, 0); ctx.lineTo(-9, -8); ctx.closePath();
      ctx.fill(); ctx.stroke(); ctx.restore();
    }
    drawScaleBar();
    window.blocklocReport.drawn = stats;
  }
  function drawScaleBar() {
    var target = 120 / view.scale, p = Math.pow(10, Math.floor(Math.log10(target))), m = p;
    [1, 2, 5, 10].forEach(function (k) { if (k * p <= target) m = k * p; });
    var len = m * view.scale, x0 = 16, y0 = H - 18;
    ctx.strokeStyle = "#e9ecef"; ctx.lineWidth = 2; ctx.beginPath();
    ctx.moveTo(x0, y0 - 5); ctx.lineTo(x0, y0); ctx.lineTo(x0 + len, y0); ctx.lineTo(x0 + len, y0 - 5); ctx.stroke();
    ctx.fillStyle = "#e9ecef"; ctx.font = "12px system-ui, sans-serif"; ctx.textAlign = "left";
    ctx.fillText(m + " m", x0 + len + 6, y0);
  }

  // pan, zoom, hover
  var drag = null;
  cv.addEventListener("mousedown", function (ev) { drag = { x: ev.clientX, y: ev.clientY, cx: view.cx, cy: view.cy }; cv.classList.add("dragging"); });
  window.addEventListener("mouseup", function () { drag = null; cv.classList.remove("dragging"); });
  cv.addEventListener("mousemove", function (ev) {
    var r = cv.getBoundingClientRect(), mx = ev.clientX - r.left, my = ev.clientY - r.top;
    if (drag) {
      view.cx = drag.cx - (ev.clientX - drag.x) / view.scale; view.cy = drag.cy + (ev.clientY - drag.y) / view.scale;
      drawTop();
    }
    var wx = view.cx + (mx - W / 2) / view.scale, wy = view.cy - (my - H / 2) / view.scale;
    document.getElementById("readout").textContent = "x " + wx.toFixed(1) + " m   y " + wy.toFixed(1) + " m";
  });
  cv.addEventListener("wheel", function (ev) {
    ev.preventDefault();
    var r = cv.getBoundingClientRect(), mx = ev.clientX - r.left, my = ev.clientY - r.top;
    var wx = view.cx + (mx - W / 2) / view.scale, wy = view.cy - (my - H / 2) / view.scale;
    var k = Math.exp(-ev.deltaY * 0.0015);
    view.scale = Math.min(2000, Math.max(1e-4, view.scale * k));
    view.cx = wx - (mx - W / 2) / view.scale; view.cy = wy + (my - H / 2) / view.scale;
    drawTop();
  }, { passive: false });
  cv.addEventListener("dblclick", function () { fit(); drawTop(); });

  // layer toggles
  var bar = document.getElementById("layers");
  LAYERS.forEach(function (l) {
    if (!(l[0] in state.layers)) return;
    var lab = document.createElement("label"), box = document.createElement("input"), sw = document.createElement("span");
    box.type = "checkbox"; box.checked = state.layers[l[0]]; box.id = "layer-" + l[0];
    box.addEventListener("change", function () { state.layers[l[0]] = box.checked; drawTop(); });
    sw.className = "swatch"; sw.style.background = l[2];
    lab.appendChild(box); lab.appendChild(sw); lab.appendChild(document.createTextNode(l[1]));
    bar.appendChild(lab);
  });

  // ------------------------------------------------------------ charts over time
  function niceStep(range, n) {
    var raw = range / Math.max(n, 1), p = Math.pow(10, Math.floor(Math.log10(raw))), best = p;
    [1, 2, 5, 10].forEach(function (k) { if (k * p <= raw * 1.5) best = k * p; });
    return best;
  }
  function chart(canvas, keys, title) {
    var r = canvas.getBoundingClientRect(), w = Math.max(1, Math.round(r.width)), h = Math.max(1, Math.round(r.height));
    canvas.width = Math.round(w * dpr); canvas.height = Math.round(h * dpr);
    var c = canvas.getContext("2d"); c.setTransform(dpr, 0, 0, dpr, 0, 0);
    c.fillStyle = "#fff"; c.fillRect(0, 0, w, h);
    var L = 54, R = 12, T = 22, B = 26, pw = w - L - R, ph = h - T - B;
    c.fillStyle = "#1d2330"; c.font = "600 13px system-ui, sans-serif"; c.textAlign = "left"; c.fillText(title, L, 15);
    keys = keys.filter(function (k) { return series[k]; });
    if (!nFrames || !keys.length) { c.fillStyle = "#868e96"; c.fillText("no data", L + 10, T + 30); return; }
    var t0 = frameT[0], t1 = frameT[nFrames - 1] > t0 ? frameT[nFrames - 1] : t0 + 1, vmax = 0;
    keys.forEach(function (k) { var s = series[k]; for (var i = 0; i < s.length; i++) if (isFinite(s[i]) && s[i] > vmax) vmax = s[i]; });
    var sorted = [];
    keys.forEach(function (k) { var s = series[k]; for (var i = 0; i < s.length; i++) if (isFinite(s[i])) sorted.push(s[i]); });
    sorted.sort(function (a, b) { return a - b; });
    var p99 = sorted.length ? sorted[Math.floor(0.995 * (sorted.length - 1))] : 1;
    vmax = Math.max(p99 * 1.15, 1e-9);  // outliers clip at the top rather than flatten the rest
    function X(t) { return L + (t - t0) / (t1 - t0) * pw; }
    function Y(v) { return T + ph - Math.min(v, vmax) / vmax * ph; }
    for (var f = 0; f < nFrames; f++) {  // shade frames that were not ok
      var code = F.status[f]; if (!BAD[code]) continue;
      var xa = X(frameT[f]), xb = f + 1 < nFrames ? X(frameT[f + 1]) : xa + 1;
      c.fillStyle = BAD[code] + "33"; c.fillRect(xa, T, Math.max(1, xb - xa), ph);
    }
    c.strokeStyle = "#e9ecef"; c.lineWidth = 1; c.fillStyle = "#5d6677"; c.font = "11px system-ui, sans-serif"; c.textAlign = "right";
    var ys = niceStep(vmax, 4);
    for (var v = 0; v <= vmax + 1e-12; v += ys) { c.beginPath(); c.moveTo(L, Y(v)); c.lineTo(L + pw, Y(v)); c.stroke(); c.fillText(+v.toPrecision(3), L - 6, Y(v) + 4); }
    c.textAlign = "center";
    var xs = niceStep(t1 - t0, 8);
    for (var t = Math.ceil(t0 / xs) * xs; t <= t1 + 1e-9; t += xs) c.fillText(+t.toPrecision(4) + " s", X(t), h - 8);
    keys.forEach(function (k) {
      var s = series[k]; c.strokeStyle = F.series[k].color; c.lineWidth = 1.3; c.beginPath(); var pen = false;
      for (var i = 0; i < s.length; i++) {
        if (!isFinite(s[i])) { pen = false; continue; }
        if (!pen) { c.moveTo(X(frameT[i]), Y(s[i])); pen = true; } else c.lineTo(X(frameT[i]), Y(s[i]));
      }
      c.stroke();
    });
    var lx = L + pw; c.textAlign = "right"; c.font = "12px system-ui, sans-serif";
    keys.slice().reverse().forEach(function (k) {
      var label = F.series[k].label; c.fillStyle = F.series[k].color; c.fillText(label, lx, 15);
      lx -= c.measureText(label).width + 16;
    });
    var xc = X(frameT[state.frame]);
    c.strokeStyle = "#f08c00"; c.lineWidth = 1.5; c.beginPath(); c.moveTo(xc, T); c.lineTo(xc, T + ph); c.stroke();
    canvas.onclick = function (ev) {
      var rr = canvas.getBoundingClientRect(), t = t0 + (ev.clientX - rr.left - L) / pw * (t1 - t0);
      setFrame(Math.min(nFrames - 1, Math.max(0, lowerBound(frameT, t))));
    };
  }
  function drawCharts() {
    chart(document.getElementById("timing"), ["update_ms", "registration_ms", "smoother_ms", "map_ms", "deskew_ms"], "per-scan time [ms]");
    chart(document.getElementById("fitness"), ["fitness"], "registration fitness");
  }

  // ------------------------------------------------------------ time slider
  var slider = document.getElementById("slider"), now = document.getElementById("now"), play = document.getElementById("play");
  slider.max = Math.max(0, nFrames - 1); slider.value = state.frame;
  function describe() {
    if (!nFrames) { now.textContent = "no frames"; return; }
    var f = state.frame, ids = Object.keys(activeAt(f));
    now.textContent = "t = " + frameT[f].toFixed(1) + " s · frame " + f + " · " + D.status_names[F.status[f]] +
      (ids.length ? " · served " + ids.join(", ") : "");
  }
  function setFrame(f) { state.frame = f; slider.value = f; describe(); drawTop(); drawCharts(); }
  slider.addEventListener("input", function () { setFrame(+slider.value); });
  play.addEventListener("click", function () {
    if (state.playing) { clearInterval(state.playing); state.playing = null; play.textContent = "play"; return; }
    if (state.frame >= nFrames - 1) state.frame = 0;
    play.textContent = "pause";
    state.playing = setInterval(function () {
      if (state.frame >= nFrames - 1) { clearInterval(state.playing); state.playing = null; play.textContent = "play"; return; }
      setFrame(Math.min(nFrames - 1, state.frame + Math.max(1, Math.round(nFrames / 600))));
    }, 40);
  });

  window.blocklocReport = { state: state, view: view, drawn: null, redraw: function () { drawTop(); drawCharts(); } };
  function all() { resize(); fit(); describe(); drawTop(); drawCharts(); }
  window.addEventListener("resize", function () { var s = view.scale, cx = view.cx, cy = view.cy; resize(); view.scale = s; view.cx = cx; view.cy = cy; drawTop(); drawCharts(); });
  all();
  window.blocklocReport.ready = true;
})();
"""
