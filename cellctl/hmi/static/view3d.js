// A small point-cloud view on a 2D canvas (no WebGL needed: works on any panel PC and headless).
// PointView(canvas, {top}) : setPoints(xyz, rgb), addPoints(xyz, rgb), draw(). Drag to turn
// (mouse or touch, pointer events), wheel or pinch-free buttons are not needed at arm's length.
"use strict";

function PointView(canvas, opts) {
  opts = opts || {};
  const ctx = canvas.getContext("2d");
  let xyz = new Float32Array(0), rgb = new Uint8Array(0), n = 0;
  // pitch 0 looks straight down (the top view); larger tilts the plate towards the viewer
  let yaw = opts.top ? 0 : -0.6, pitch = opts.top ? 0 : 0.9;
  let zScale = opts.zScale || 1;
  let pending = false;
  const self = {};

  function grow(cap) {
    if (cap <= xyz.length / 3) return;
    const c = Math.max(cap, 2 * xyz.length / 3 + 1024);
    const nx = new Float32Array(c * 3); nx.set(xyz.subarray(0, n * 3)); xyz = nx;
    const nc = new Uint8Array(c * 3); nc.set(rgb.subarray(0, n * 3)); rgb = nc;
  }
  self.count = () => n;
  self.setZScale = (s) => { zScale = s; self.draw(); };
  self.setPoints = (p, c) => { n = 0; self.addPoints(p, c); };
  self.addPoints = (p, c) => {
    const m = p.length / 3;
    grow(n + m);
    xyz.set(p, n * 3); rgb.set(c, n * 3); n += m;
    self.draw();
  };
  self.draw = () => {
    if (pending) return;
    pending = true;
    requestAnimationFrame(render);
  };

  function render() {
    pending = false;
    const W = canvas.width, H = canvas.height;
    const img = ctx.createImageData(W, H);
    const d = img.data;
    for (let i = 3; i < d.length; i += 4) { d[i - 3] = 6; d[i - 2] = 9; d[i - 1] = 11; d[i] = 255; }
    if (n === 0) { ctx.putImageData(img, 0, 0); return; }
    let lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (let i = 0; i < n; i++) for (let k = 0; k < 3; k++) {
      const v = xyz[3 * i + k]; if (v < lo[k]) lo[k] = v; if (v > hi[k]) hi[k] = v;
    }
    const c = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2];
    const cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
    const span = Math.max(hi[0] - lo[0], hi[1] - lo[1], 1);
    const s = 0.9 * Math.min(W, H * (opts.top ? (hi[0] - lo[0] + 1) / (hi[1] - lo[1] + 1) : 1.6)) / span;
    const z = new Float32Array(W * H).fill(-Infinity);
    for (let i = 0; i < n; i++) {
      const x = xyz[3 * i] - c[0], y = xyz[3 * i + 1] - c[1], h = (xyz[3 * i + 2] - c[2]) * zScale;
      // turn about z (yaw), then tilt about the screen's x axis (pitch)
      const xr = cy * x - sy * y, yr = sy * x + cy * y;
      const sx = xr, syy = cp * yr - sp * h, depth = sp * yr + cp * h;
      const px = Math.round(W / 2 + s * sx), py = Math.round(H / 2 - s * syy);
      for (let oy = 0; oy < 2; oy++) for (let ox = 0; ox < 2; ox++) {
        const qx = px + ox, qy = py + oy;
        if (qx < 0 || qy < 0 || qx >= W || qy >= H) continue;
        const j = qy * W + qx;
        if (depth < z[j]) continue;
        z[j] = depth;
        d[4 * j] = rgb[3 * i]; d[4 * j + 1] = rgb[3 * i + 1]; d[4 * j + 2] = rgb[3 * i + 2];
      }
    }
    ctx.putImageData(img, 0, 0);
  }

  if (!opts.top) {
    let drag = null;
    canvas.addEventListener("pointerdown", (e) => { drag = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
    canvas.addEventListener("pointermove", (e) => {
      if (!drag) return;
      yaw += (e.clientX - drag[0]) * 0.01;
      pitch = Math.max(0.05, Math.min(Math.PI / 2, pitch + (e.clientY - drag[1]) * 0.01));
      drag = [e.clientX, e.clientY];
      self.draw();
    });
    canvas.addEventListener("pointerup", () => { drag = null; });
  }
  return self;
}

// height -> colour (blue low, red high) over [lo, hi]
function heightColours(xyz, lo, hi) {
  const m = xyz.length / 3, out = new Uint8Array(m * 3);
  for (let i = 0; i < m; i++) {
    const t = Math.max(0, Math.min(1, (xyz[3 * i + 2] - lo) / Math.max(hi - lo, 1e-6)));
    out[3 * i] = Math.round(60 + 195 * t); out[3 * i + 1] = Math.round(120 + 100 * (1 - Math.abs(2 * t - 1))); out[3 * i + 2] = Math.round(255 - 195 * t);
  }
  return out;
}

// deviation (mm) -> tolerance band colour: within the standard range, within the limit, beyond
const BAND = { std: [40, 170, 70], limit: [230, 170, 30], out: [220, 50, 50] };
function bandColour(dev, stdMm, limitMm) {
  const a = Math.abs(dev);
  return a <= stdMm ? BAND.std : a <= limitMm ? BAND.limit : BAND.out;
}
