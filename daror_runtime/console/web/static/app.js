// The operator's web console: renders the runtime's status, posts console lines, plots live rows.
"use strict";
const $ = (id) => document.getElementById(id);
const WINDOW_S = 20;
const daror = (window.daror = { rowsReceived: 0, referenceRows: 0, messages: 0, answers: 0, status: null, lastAnswer: null });
const JOINTS = [0, 1, 2, 3];
const charts = {
  q: new LiveChart($("plot-q"), { series: JOINTS.map((j) => ({ label: "q" + (j + 1), color: JOINT_COLORS[j] })), windowS: WINDOW_S, height: 190 }),
  tau: new LiveChart($("plot-tau"), {
    series: [...JOINTS.map((j) => ({ label: "measured " + (j + 1), color: JOINT_COLORS[j] })),
      ...JOINTS.map((j) => ({ label: "model " + (j + 1), color: JOINT_COLORS[j], dash: [6, 4] }))],
    windowS: WINDOW_S, height: 240,
  }),
};
const CHECKLIST = { settings: "settings", pilot_installation: "installation", safety_experience: "safety_experience", rom_limits: "a_priori_model" };
const EVENT_LINE = { advance: "advance", revert: "revert", reset: "reset", acknowledge: "ack" };
const REACTION_TEXT = { off: "torque off", lower: "hold, lower to the rest, torque off", hold: "hold" };
let fsm = null;
let sliderBusy = false;

function esc(s) { return String(s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" }[c])); }

async function send(line) {
  const r = await fetch("/api/command", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify({ line }) });
  const answer = await r.json();
  daror.lastAnswer = answer;
  daror.answers++;
  $("answer").textContent = "> " + answer.line + "\n" + answer.answer;
  $("answer").className = answer.ok ? "" : "refused";
  if (answer.status) render(answer.status);
  return answer;
}
daror.send = send;

let fsmDrawn = false;
function drawFsm(current) {
  if (!fsm) return;
  if (!fsmDrawn) { FsmDiagram.draw($("fsm"), fsm); fsmDrawn = true; }
  FsmDiagram.highlight($("fsm"), current);
}

function render(st) {
  daror.status = st;
  $("state-badge").textContent = st.state + (st.superstate ? " (" + st.superstate + ")" : "");
  $("state-badge").className = "badge " + (st.number === null ? "bad" : "ok");
  $("state-badge").dataset.state = st.state;
  $("pilot-badge").textContent = st.pilot === null ? "no pilot named" : "pilot " + st.pilot;
  $("pilot-badge").className = "badge " + (st.pilot === null ? "bad" : "ok");
  $("state-description").textContent = st.description + " — mode " + st.mode;
  const pressed = Object.entries(st.estop_pressed).filter(([, v]) => v).map(([k]) => k);
  $("estop-badge").textContent = pressed.length ? "E-STOP: " + pressed.join(", ") : "e-stops released (tested: " + (st.estop_tested.join(", ") || "none") + ")";
  $("estop-badge").className = "badge " + (pressed.length ? "bad" : "ok");
  $("fault-badge").textContent = st.faults.length ? st.faults.length + " fault(s)" : "no faults";
  $("fault-badge").className = "badge " + (st.faults.length ? "bad" : "ok");
  $("clock").textContent = st.t_s === null ? "" : "t = " + st.t_s.toFixed(1) + " s, " + st.loop.clock + ", worst lateness " + st.loop.worst_lateness_ms.toFixed(2) + " ms"
    + (st.loop.clock === "paced" ? ", " + st.loop.stalls + " stalls (not faults), " + st.loop.behind_ms.toFixed(0) + " ms behind" : "");
  drawFsm(st.state);
  // operator events: a button each, disabled with the unmet guards beside it
  let ev = "";
  for (const [event, line] of Object.entries(EVENT_LINE)) {
    const gate = st.gates[event];
    let why = "", ready = false;
    if (!gate || !gate.possible) why = `<span class="small">${esc(gate ? gate.why_not || "not from this state" : "not from this state")}</span>`;
    else {
      const unmet = gate.guards.filter((g) => !g.holds);
      ready = unmet.length === 0;
      why = ready ? `<span class="met">ready${gate.guards.length ? ": " + gate.guards.map((g) => esc(g.name)).join(", ") + " hold" : ""}</span>`
        : `<span class="unmet" id="unmet-${event}">blocked by: ${unmet.map((g) => `<b>${esc(g.name)}</b> (${esc(g.description)})`).join("; ")}</span>`;
    }
    ev += `<div class="event"><button id="event-${event}" data-line="${line}" ${ready ? "" : "disabled"}>${event}</button>${why}</div>`;
  }
  $("events").innerHTML = ev;
  // checklists of this state
  const checklist = CHECKLIST[st.state];
  let cl = "";
  if (checklist) {
    const done = st.confirmed.includes(checklist);
    cl = `<div class="row"><button id="confirm-${checklist}" data-line="confirm ${checklist}" ${done ? "disabled" : ""}>confirm ${checklist.replace(/_/g, " ")}</button><span class="${done ? "met" : "unmet"}">${done ? "confirmed" : "not confirmed"}</span></div>`;
  }
  $("checklists").innerHTML = cl || '<span class="small">no checklist in this state</span>';
  $("next-steps").innerHTML = st.next_steps.map((s) => `<li>${esc(s.what)}${s.type.length ? " <code>" + s.type.map(esc).join(" ; ") + "</code>" : ""}</li>`).join("");
  $("world-card").style.display = st.has_world ? "" : "none";
  // support
  if (!sliderBusy) $("support").value = st.support_level;
  $("support-value").textContent = Number(st.support_level).toFixed(2);
  $("support-delivered").textContent = "delivered " + Number(st.delivered_support_level).toFixed(2);
  // the online indicators per model (issue 29, docs/online.md): the pilot's effort at rest, the support measured
  const nm = (v) => v.map((x) => (x === null ? "–" : Number(x).toFixed(2))).join(" ");
  $("online").innerHTML = (st.online || []).map((o) => `<div>${esc(o.model)}: `
    + (o.last_rest ? `his effort at the last rest <b>${nm(o.last_rest.effort_nm)}</b> Nm` : "no rest yet")
    + `; ${o.rests} rests` + (o.level_delivered === null ? "" : `; support measured ${Number(o.level_delivered).toFixed(2)}`)
    + (o.moving_samples.some((n) => n > 0) ? `; moving: interaction RMS ${nm(o.interaction_rms_nm)} Nm` : "")
    + ((o.drift_tests || []).length ? `; drift tests ${o.drift_tests.length}, the last: unsupported <b>${nm(o.drift_tests[o.drift_tests.length - 1].unsupported_nm)}</b> Nm` : "")
    + "</div>").join("")
    + (st.comparison ? `<div>${st.comparison.verdict_text ? esc(st.comparison.verdict_text)
      : st.comparison.why_stopped ? "blind comparison stopped: " + esc(st.comparison.why_stopped)
      : `blind comparison: block ${st.comparison.block} of ${st.comparison.blocks} (${esc(st.comparison.phase)}; ${st.comparison.rated} rated; the model is not shown)`}</div>` : "");
  // model
  const m = st.model;
  $("model").innerHTML = m ? `<b>${esc(m.name)}</b> (${esc(m.kind)}) — ${m.validated ? "validated, RMSE " + m.validation_rmse_nm.toFixed(3) + " Nm" : "approved: " + esc(m.approved_by)}`
    + (m.validation_data ? `<div class="small" id="model-validation-data">validation data: ${esc(m.validation_data)}</div>` : "")
    + (m.validation_extrapolation ? `<div class="small">${esc(m.validation_extrapolation)}</div>` : "")
    + (m.nonconservative_confirmed ? `<div class="refused">NOT conservative (${Number(m.closed_path_energy_j[m.closed_path_energy_j.length - 1]).toPrecision(3)} J over the closed path): used because the operator confirmed it</div>` : "")
    : '<span class="small">no model in use</span>';
  const r = st.model_refused;
  $("model-refused").textContent = !r ? "" : r.validated
    ? "refused: " + r.name + " is not conservative (" + Number(r.closed_path_energy_j[r.closed_path_energy_j.length - 1]).toPrecision(3) + " J over the closed path); 'model FILE VALIDATION nonconservative' uses it anyway"
    : "refused: " + r.name + ", validation RMSE " + Number(r.validation_rmse_nm).toFixed(3) + " Nm (limit " + r.max_validation_rmse_nm + " Nm): never used";
  $("isb").textContent = st.isb_limits_deg ? Object.entries(st.isb_limits_deg).map(([k, v]) => `${k} ${v[0].toFixed(0)}..${v[1].toFixed(0)}°`).join(", ") : (st.rom_recording ? "recording…" : "not recorded");
  const run = st.identification_running;
  const pairs = (o) => Object.entries(o).map(([k, v]) => `${k.replace(/_/g, " ")}: ${typeof v === "number" ? Number(v.toFixed(3)) : (typeof v === "object" && v !== null ? JSON.stringify(v) : v)}`).join(", ");
  $("identification").textContent = run ? `running: ${Math.min(100, 100 * run.elapsed_s / run.duration_s).toFixed(0)} % — ` + pairs(run) : (st.jobs_pending ? "work running outside the loop (saving data, training)…" : (st.last_identification ? "last run: " + pairs(st.last_identification) : "no run"));
  $("faults").innerHTML = st.faults.map((f) => `<li class="refused">${esc(f.kind || "")}: ${esc(f.reason || f.message || JSON.stringify(f))}</li>`).join("") || '<li class="small">none</li>';
  for (const note of st.notes || []) $("faults").innerHTML += `<li class="small">note: ${esc(note)}</li>`;
  // the fault's reaction (docs/safety.md): what the robot does with the pilot's arm, and the operator's two choices
  const rx = st.reaction;
  $("reaction").innerHTML = rx ? `reaction: <b>${esc(REACTION_TEXT[rx.reaction] || rx.reaction)}</b> (category ${rx.category}; ${rx.causes.map(esc).join(", ")}${rx.joints_off.length ? "; joint(s) " + rx.joints_off.join(", ") + " off" : ""}; support ${esc(rx.support)})`
    + (rx.phase ? `<br>now: <b id="reaction-phase">${esc(rx.phase)}</b>${rx.note ? ": " + esc(rx.note) : ""}` : "") : "no reaction";
  $("reaction").className = rx && rx.arm_held ? "unmet" : "small";
  $("lower-arm").disabled = !(rx && rx.arm_held && rx.lowering_refused === null);
  $("release-arm").disabled = !(rx && rx.arm_held);
  $("reaction-why").textContent = rx && rx.arm_held && rx.lowering_refused ? "lower: " + rx.lowering_refused : "";
}

function addLog(lines) {
  if (!lines.length) return;
  const el = $("log");
  el.textContent = (el.textContent + lines.join("\n") + "\n").split("\n").slice(-300).join("\n");
  el.scrollTop = el.scrollHeight;
}

let lastCount = 0, lastTime = performance.now();
function connect() {
  const ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws");
  ws.onopen = () => { $("conn").textContent = "live"; $("conn").className = "badge ok"; };
  ws.onclose = () => { $("conn").textContent = "disconnected: retrying"; $("conn").className = "badge off"; setTimeout(connect, 1000); };
  ws.onmessage = (msg) => {
    const m = JSON.parse(msg.data);
    daror.messages++;
    for (const row of m.rows) { // t, q (deg) x4, measured spring torques x4, model x support x4 (null: not compensating)
      charts.q.push(row[0], row.slice(1, 5));
      charts.tau.push(row[0], row.slice(5, 13));
      if (row[9] !== null) daror.referenceRows++;
    }
    daror.rowsReceived += m.rows.length;
    addLog(m.log);
    if (m.status) render(m.status);
  };
}

const DRAW_EVERY_MS = 100; // 10 frames/s: the plots move smoothly enough, the lab PC keeps its CPU for the loop
let lastDraw = 0;
function frame() {
  const now = performance.now();
  if (now - lastDraw >= DRAW_EVERY_MS) { lastDraw = now; charts.q.draw(); charts.tau.draw(); }
  if (now - lastTime > 1000) {
    $("rate").textContent = ((daror.rowsReceived - lastCount) * 1000 / (now - lastTime)).toFixed(0) + " rows/s";
    lastCount = daror.rowsReceived; lastTime = now;
  }
  requestAnimationFrame(frame);
}

document.addEventListener("click", (e) => {
  const b = e.target.closest("button[data-line]");
  if (b && !b.disabled) send(b.dataset.line);
});
$("send").onclick = () => { const v = $("line").value.trim(); if (v) send(v); };
$("line").addEventListener("keydown", (e) => { if (e.key === "Enter") $("send").click(); });
$("model-select").onclick = () => send(("model " + $("model-file").value.trim() + " " + $("model-validation").value.trim()).trim());
$("isb-load").onclick = () => send("rom load " + $("isb-file").value.trim());
$("support").addEventListener("input", () => { sliderBusy = true; $("support-value").textContent = Number($("support").value).toFixed(2); });
$("support").addEventListener("change", async () => { await send("support " + $("support").value); sliderBusy = false; });

(async () => {
  fsm = await (await fetch("/api/fsm")).json();
  render(await (await fetch("/api/status")).json());
  connect();
  requestAnimationFrame(frame);
})();
