// The FSM diagram of the operator console: draws the layout computed by
// daror_runtime.fsm.diagram.layout() (GET /api/fsm) as an inline SVG and highlights the current state.
// Plain browser JS, no libraries (the lab PC is offline).
//
//   FsmDiagram.draw(container, layout)     replace container's content with the diagram
//   FsmDiagram.highlight(container, name)  mark the node of state `name` (class "current") and no other
//
// Lengths in the layout are abstract units; the SVG's viewBox is the layout's width x height and the
// drawing scales to the container's width. State nodes are <g class="fsm-state" id="fsm-<name>">
// (plus "test" for the e-stop test states and "fail" for FAIL).
"use strict";

(function () {
  const SVG = "http://www.w3.org/2000/svg";
  const LABEL_FONT = 7; // units; monospace, so a character is 0.6 em wide
  const LABEL_CHAR = 0.6 * LABEL_FONT;
  const LABEL_LINE = 8; // units between label baselines
  const NAME_FONT = 10;
  const NAME_CHAR = 0.58 * NAME_FONT; // an estimate for a bold sans-serif
  let drawings = 0; // makes the marker ids of several diagrams on one page unique

  const STYLE = `
    .fsm-diagram { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; }
    .fsm-diagram .fsm-band rect { fill: #f8fafc; stroke: #94a3b8; stroke-width: 1; stroke-dasharray: 5 3; }
    .fsm-diagram .fsm-band text { fill: #475569; font-size: 9px; font-weight: 600; }
    .fsm-diagram .fsm-state rect { fill: #ffffff; stroke: #64748b; stroke-width: 1; }
    .fsm-diagram .fsm-state text { fill: #0f172a; font-size: ${NAME_FONT}px; font-weight: 600; }
    .fsm-diagram .fsm-state text.tag { fill: #b45309; font-size: 7px; font-weight: 400; }
    .fsm-diagram .fsm-state.test rect { stroke: #b45309; }
    .fsm-diagram .fsm-state.fail rect { stroke: #b91c1c; stroke-width: 1.5; }
    .fsm-diagram .fsm-state.fail text { fill: #b91c1c; }
    .fsm-diagram .fsm-state.current rect { fill: #2563eb; stroke: #1d4ed8; }
    .fsm-diagram .fsm-state.current text { fill: #ffffff; }
    .fsm-diagram .fsm-state.fail.current rect { fill: #b91c1c; stroke: #7f1d1d; }
    .fsm-diagram .fsm-state.fail.current text { fill: #ffffff; }
    .fsm-diagram .fsm-edge .route { fill: none; stroke: #475569; stroke-width: 1; }
    .fsm-diagram .fsm-edge.revert .route { stroke-dasharray: 4 3; }
    .fsm-diagram .fsm-edge.reset .route { stroke-dasharray: 1 2.5; stroke-linecap: round; stroke-width: 1.2; }
    .fsm-diagram .fsm-edge .hit { fill: none; stroke: transparent; stroke-width: 7; pointer-events: stroke; }
    .fsm-diagram .fsm-edge:hover .route { stroke: #0f172a; stroke-width: 1.6; }
    .fsm-diagram .fsm-edge text { font-family: ui-monospace, "DejaVu Sans Mono", Menlo, Consolas, monospace;
                                  font-size: ${LABEL_FONT}px; fill: #64748b; }
    .fsm-diagram .fsm-edge text .event { fill: #334155; font-weight: 700; }
    .fsm-diagram .fsm-notes { fill: #475569; font-size: 7px; }
  `;

  function el(name, attrs, parent) {
    const node = document.createElementNS(SVG, name);
    for (const [key, value] of Object.entries(attrs || {})) node.setAttribute(key, String(value));
    if (parent) parent.appendChild(node);
    return node;
  }

  function text(parent, x, y, content, attrs) {
    const node = el("text", Object.assign({ x: x, y: y }, attrs || {}), parent);
    node.textContent = content;
    return node;
  }

  function title(parent, content) {
    const node = el("title", {}, parent);
    node.textContent = content;
    return node;
  }

  // `words` wrapped greedily into lines of at most `maxChars` characters (a word longer than a line gets its own).
  function wrap(words, maxChars) {
    const lines = [];
    let line = "";
    for (const word of words) {
      const candidate = line ? line + " " + word : word;
      if (candidate.length <= maxChars || !line) {
        line = candidate;
      } else {
        lines.push(line);
        line = word;
      }
    }
    if (line) lines.push(line);
    return lines;
  }

  // The label lines of an edge: the event and its guards if they fit the label area, else the event alone.
  function labelLines(edge) {
    const maxChars = Math.floor(edge.label_w / LABEL_CHAR);
    const maxLines = Math.max(1, Math.floor((edge.label_h - LABEL_FONT) / LABEL_LINE) + 1);
    if (edge.guards.length) {
      const words = [edge.event, ...edge.guards.map((g, i) => (i === 0 ? "[" : "") + g + (i === edge.guards.length - 1 ? "]" : ","))];
      const lines = wrap(words, maxChars);
      if (lines.length <= maxLines && lines.every((l) => l.length <= maxChars)) return lines;
    }
    return [edge.event];
  }

  function drawBand(svg, band) {
    const g = el("g", { class: "fsm-band" }, svg);
    title(g, band.description ? `${band.name}: ${band.description}` : band.name);
    el("rect", { x: band.x, y: band.y, width: band.w, height: band.h, rx: 4 }, g);
    text(g, band.x + band.w - 6, band.y + 12, band.name, { "text-anchor": "end" });
  }

  function drawState(svg, state) {
    const classes = ["fsm-state"];
    if (state.fail) classes.push("fail");
    if (state.test) classes.push("test");
    const g = el("g", { id: "fsm-" + state.name, class: classes.join(" ") }, svg);
    const label = state.number === null || state.number === undefined ? state.name : `${state.number}. ${state.name}`;
    const where = state.superstate ? ` (${state.superstate})` : "";
    const lines = [label + where];
    if (state.description) lines.push(state.description);
    lines.push("mode: " + state.mode);
    if (state.test) lines.push("e-stop test state: a fault is met by its reaction and recorded, no FAIL");
    title(g, lines.join("\n"));
    el("rect", { x: state.x, y: state.y, width: state.w, height: state.h, rx: 3 }, g);
    const tag = state.test ? "e-stop test" : "";
    const tagWidth = tag ? tag.length * 0.6 * 7 + 6 : 0;
    const room = state.w - 12 - tagWidth;
    const name = text(g, state.x + 6, state.y + state.h / 2 + NAME_FONT * 0.35, label);
    if (label.length * NAME_CHAR > room) {
      name.setAttribute("textLength", String(room));
      name.setAttribute("lengthAdjust", "spacingAndGlyphs");
    }
    if (tag) {
      text(g, state.x + state.w - 5, state.y + state.h / 2 + 2.5, tag, { class: "tag", "text-anchor": "end" });
    }
  }

  function drawEdge(svg, edge, markerId) {
    const g = el("g", { class: "fsm-edge " + edge.event, "data-source": edge.source, "data-dest": edge.dest }, svg);
    const guards = edge.guards.length ? "\nguards: " + edge.guards.join(", ") : "\nno guards";
    title(g, `${edge.source} \u2192 ${edge.dest}: ${edge.event}${guards}`);
    const d = edge.points.map((p, i) => (i === 0 ? "M" : "L") + p[0] + "," + p[1]).join(" ");
    el("path", { d: d, class: "hit" }, g);
    el("path", { d: d, class: "route", "marker-end": `url(#${markerId})` }, g);
    labelLines(edge).forEach((line, i) => {
      const node = el("text", { x: edge.label_x, y: edge.label_y + LABEL_FONT + i * LABEL_LINE }, g);
      let rest = line;
      if (i === 0 && line.startsWith(edge.event)) {
        const event = el("tspan", { class: "event" }, node);
        event.textContent = edge.event;
        rest = line.slice(edge.event.length);
      }
      if (rest) node.appendChild(document.createTextNode(rest));
    });
  }

  function draw(container, layout) {
    const previous = container.querySelector(".fsm-state.current");
    const current = previous ? previous.id.slice("fsm-".length) : null;
    drawings += 1;
    const markerId = "fsm-arrow-" + drawings;
    const svg = el("svg", {
      class: "fsm-diagram",
      viewBox: `0 0 ${layout.width} ${layout.height}`,
      width: "100%",
      role: "img",
      "aria-label": "state diagram of the safety FSM",
    });
    svg.style.display = "block";
    svg.style.maxWidth = "100%";
    svg.style.height = "auto";
    el("style", {}, svg).textContent = STYLE;
    const defs = el("defs", {}, svg);
    const marker = el(
      "marker",
      { id: markerId, viewBox: "0 0 8 8", refX: 8, refY: 4, markerWidth: 6, markerHeight: 6, markerUnits: "userSpaceOnUse", orient: "auto" },
      defs,
    );
    el("path", { d: "M0,0 L8,4 L0,8 z", fill: "#475569" }, marker);

    for (const band of layout.superstates) drawBand(svg, band);
    for (const edge of layout.edges) drawEdge(svg, edge, markerId);
    for (const state of layout.states) drawState(svg, state);
    const notes = el("g", { class: "fsm-notes" }, svg);
    for (const line of layout.note_lines || []) text(notes, line.x, line.y, line.text);

    container.textContent = "";
    container.appendChild(svg);
    if (current) highlight(container, current);
    return svg;
  }

  function highlight(container, stateName) {
    let found = false;
    for (const node of container.querySelectorAll(".fsm-state")) {
      const isCurrent = stateName !== null && stateName !== undefined && node.id === "fsm-" + stateName;
      node.classList.toggle("current", isCurrent);
      found = found || isCurrent;
    }
    return found;
  }

  window.FsmDiagram = { draw: draw, highlight: highlight };
})();
