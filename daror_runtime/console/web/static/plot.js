// A small streaming plotter on a canvas (no dependency: the lab PC is offline).
// StripChart(canvas, series, windowS): push(t, values) appends; draw() redraws the last windowS seconds.
"use strict";
const COLORS = ["#2563eb", "#dc2626", "#16a34a", "#9333ea"];

class StripChart {
  constructor(canvas, series, windowS, capacity) {
    this.canvas = canvas; this.series = series; this.windowS = windowS;
    this.capacity = capacity || 1600;
    this.t = new Float64Array(this.capacity);
    this.v = Array.from({ length: series }, () => new Float64Array(this.capacity));
    this.start = 0; this.count = 0; this.points = 0;
  }
  push(t, values) {
    const i = (this.start + this.count) % this.capacity;
    this.t[i] = t;
    for (let s = 0; s < this.series; s++) this.v[s][i] = values[s];
    if (this.count < this.capacity) this.count++; else this.start = (this.start + 1) % this.capacity;
    this.points++;
  }
  at(k) { return (this.start + k) % this.capacity; }
  draw() {
    const c = this.canvas, dpr = window.devicePixelRatio || 1;
    const w = c.clientWidth, h = c.clientHeight;
    if (c.width !== w * dpr || c.height !== h * dpr) { c.width = w * dpr; c.height = h * dpr; }
    const g = c.getContext("2d");
    g.setTransform(dpr, 0, 0, dpr, 0, 0);
    g.clearRect(0, 0, w, h);
    if (this.count < 2) return;
    const tEnd = this.t[this.at(this.count - 1)], tStart = tEnd - this.windowS;
    let lo = Infinity, hi = -Infinity, first = 0;
    while (first < this.count && this.t[this.at(first)] < tStart) first++;
    for (let k = first; k < this.count; k++) {
      const i = this.at(k);
      for (let s = 0; s < this.series; s++) { const y = this.v[s][i]; if (y < lo) lo = y; if (y > hi) hi = y; }
    }
    if (hi - lo < 1e-6) { hi += 0.5; lo -= 0.5; }
    const pad = 0.08 * (hi - lo); lo -= pad; hi += pad;
    const left = 40, right = w - 4, top = 4, bottom = h - 16;
    const X = (t) => left + (right - left) * (t - tStart) / this.windowS;
    const Y = (y) => bottom - (bottom - top) * (y - lo) / (hi - lo);
    g.strokeStyle = "#e5e7eb"; g.fillStyle = "#6b7280"; g.font = "10px sans-serif"; g.lineWidth = 1;
    for (let k = 0; k <= 4; k++) {
      const y = lo + (hi - lo) * k / 4, py = Y(y);
      g.beginPath(); g.moveTo(left, py); g.lineTo(right, py); g.stroke();
      g.fillText(y.toFixed(1), 2, py + 3);
    }
    for (let s = Math.ceil(tStart / 5) * 5; s <= tEnd; s += 5) g.fillText(s.toFixed(0) + " s", X(s) - 8, h - 3);
    g.lineWidth = 1.5;
    for (let s = 0; s < this.series; s++) {
      g.strokeStyle = COLORS[s % COLORS.length]; g.beginPath();
      for (let k = first; k < this.count; k++) {
        const i = this.at(k);
        if (k === first) g.moveTo(X(this.t[i]), Y(this.v[s][i])); else g.lineTo(X(this.t[i]), Y(this.v[s][i]));
      }
      g.stroke();
    }
  }
}
window.StripChart = StripChart;
