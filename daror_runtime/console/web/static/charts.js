// Live strip charts of the last windowS seconds, drawn by uPlot (vendored in static/vendor: the lab PC is offline).
// new LiveChart(element, {series: [{label, color, dash}], windowS, height}); push(t, values) appends a row
// (null: no value, drawn as a gap); draw() trims to the window and redraws (called at the page's frame rate).
"use strict";
const JOINT_COLORS = ["#2563eb", "#dc2626", "#16a34a", "#9333ea"];

class LiveChart {
  constructor(element, { series, windowS, height }) {
    this.windowS = windowS;
    this.n = series.length;
    this.height = height;
    this.data = [[], ...series.map(() => [])];
    this.dirty = false;
    this.plot = new uPlot({
      width: Math.max(200, element.clientWidth), height,
      scales: { x: { time: false } },
      legend: { show: false }, cursor: { show: false },
      series: [{ label: "t (s)" }, ...series.map((s) => ({ label: s.label, stroke: s.color, width: 1.5, dash: s.dash, spanGaps: false, points: { show: false } }))],
      axes: [{ values: (u, ticks) => ticks.map((v) => v.toFixed(0) + " s") }, { size: 46 }],
    }, this.data, element);
    new ResizeObserver(() => this.plot.setSize({ width: Math.max(200, element.clientWidth), height: this.height })).observe(element);
  }
  push(t, values) {
    const times = this.data[0];
    if (times.length && t < times[times.length - 1]) for (const column of this.data) column.length = 0; // time went back: a new run
    times.push(t);
    for (let s = 0; s < this.n; s++) this.data[s + 1].push(values[s]);
    this.dirty = true;
  }
  draw() {
    if (!this.dirty) return;
    this.dirty = false;
    const times = this.data[0], from = times[times.length - 1] - this.windowS;
    let old = 0;
    while (old < times.length && times[old] < from) old++;
    if (old > 0) for (const column of this.data) column.splice(0, old);
    this.plot.setData(this.data);
  }
}
window.LiveChart = LiveChart;
window.JOINT_COLORS = JOINT_COLORS;
