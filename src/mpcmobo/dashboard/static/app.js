// The page: polls /api/state every 2 s and redraws what changed; nothing is ever written.
"use strict";

const POLL_MS = 2000;
let state = { version: null, runs: [] };
let episodeKey = null;   // the trajectory shown: "run|learner|seed|phase|episode|start"
let objectiveKey = null; // the job whose f1..f4 are shown: "run|learner|seed"

function el(tag, text, cls) {
  const e = document.createElement(tag);
  if (text !== undefined && text !== null) e.textContent = text;
  if (cls) e.className = cls;
  return e;
}

function table(id, head, rows, textCols = 0) {
  const t = document.getElementById(id);
  t.textContent = "";
  const tr = el("tr");
  head.forEach((h, i) => tr.appendChild(el("th", h, i < textCols ? "text" : "")));
  t.appendChild(tr);
  rows.forEach((row) => {
    const r = el("tr");
    row.forEach((v, i) => r.appendChild(el("td", fmt(v), i < textCols ? "text" : "")));
    t.appendChild(r);
  });
}

function lastFinite(values) {
  for (let i = values.length - 1; i >= 0; i--) if (values[i] !== null) return values[i];
  return null;
}

function drawMessages(runs) {
  const box = document.getElementById("messages");
  box.textContent = "";
  runs.forEach((run) => (run.messages || []).forEach((m) => box.appendChild(el("div", m, "message"))));
}

function drawJobs(runs) {
  const rows = [];
  runs.forEach((run) => (run.jobs || []).forEach((job) => {
    const J = lastFinite(job.J_eval);
    const n = job.episode.length;
    rows.push([run.name, job.learner, job.seed, `${n}${run.budget ? " / " + run.budget : ""}`,
      job.state,
      n ? job.cost[n - 1] : null, n ? job.cum_cost[n - 1] : null, J,
      J !== null && run.J_star ? J / run.J_star : null, run.J_star, run.J_initial,
      job.changes.length, (job.refused || []).length, job.errors.length]);
  }));
  table("jobs", ["run", "learner", "seed", "episodes", "state", "last plant cost",
    "cumulative plant cost", "J_eval deployed", "J_eval / J*", "J*", "J_eval(theta0)",
    "deployments", "refused candidates", "failed episodes"], rows, 3);
}

function drawChanges(runs) {
  const rows = [];
  runs.forEach((run) => (run.jobs || []).forEach((job) => job.changes.forEach((c) => {
    const what = c.changed.map(([n, a, b]) => `${n}: ${fmt(a)} -> ${fmt(b)}`).join(", ");
    rows.push([run.name, job.learner, job.seed, what || (c.first ? "first deployed theta" : ""),
      c.episode, c.new_runs, c.new_cost, c.old_runs, c.old_cost, c.J_eval, job.deploy || "default"]);
  })));
  table("changes", ["run", "learner", "seed", "changed", "after episode", "episodes of new theta",
    "their mean plant cost", "episodes of old theta", "their mean plant cost",
    "J_eval after", "deploy test"], rows, 4);
}

// status.json's keys with a place of their own (the others are listed as they are)
const SHOWN = new Set(["recommendation", "plant_cost", "excess_cost", "quarantined", "pending", "trials", "identification", "learning"]);

// a value of status.json in words: a list joined, a table as "key: value; ...", a number formatted
function words(v) {
  if (v === null || v === undefined) return "-";
  if (Array.isArray(v)) return v.length ? v.map(words).join(", ") : "none";
  if (typeof v === "object") return Object.entries(v).map(([k, x]) => `${k}: ${words(x)}`).join("; ");
  return typeof v === "number" ? fmt(v) : String(v);
}

function drawTuner(runs) {
  const tuners = runs.filter((r) => r.tuner);
  document.getElementById("tuner-section").hidden = !tuners.length;
  const box = document.getElementById("tuner");
  box.textContent = "";
  tuners.forEach((run) => {
    const t = run.tuner, known = !!t.status, s = t.status || {};
    const dl = el("dl");
    let pending = t.pending ? `trial ${t.pending.episode}` + (t.pending.theta ? ` theta [${t.pending.theta.map((v) => fmt(v)).join(", ")}]` : "") : "none";
    if (s.learning !== null && s.learning !== undefined) pending = `trial ${s.learning}: told, its log not learned from yet`;
    const rec = s.recommendation;
    const said = rec === undefined || rec === null ? "not recorded" : (typeof rec === "string" ? rec : `${rec.action}: ${rec.reason}`);
    [["run", run.path], ["pending trial", pending], ["recommendation", said],
      ["cumulative plant cost", fmt(s.plant_cost)], ["cumulative excess cost", fmt(s.excess_cost)],
      ["quarantined trials", known ? words(s.quarantined || []) : "unknown (no readable status.json)"],
      ...Object.entries(s).filter(([k]) => !SHOWN.has(k)).map(([k, v]) => [k, words(v)])].forEach(([k, v]) => {
      dl.appendChild(el("dt", k)); dl.appendChild(el("dd", v));
    });
    box.appendChild(dl);
    const trials = Array.isArray(s.trials) ? s.trials : [];
    if (trials.length) {
      const id = `trials-${run.index}`;
      const t2 = el("table"); t2.id = id; box.appendChild(t2);
      const keys = [...new Set(trials.flatMap((r) => Object.keys(r)))];
      table(id, keys, trials.map((r) => keys.map((k) => (typeof r[k] === "object" && r[k] !== null ? words(r[k]) : r[k]))));
    }
  });
}

function trajectoryOptions(runs) {
  const sel = document.getElementById("trajectory");
  const keys = [];
  runs.forEach((run) => (run.trajectories || []).forEach(([learner, seed, phase, episode, start]) => {
    const who = learner ? `${learner} s${seed}` : "reference";
    keys.push([`${run.index}|${learner}|${seed}|${phase}|${episode}|${start}`,
      `${runs.length > 1 ? run.name + ": " : ""}${who} ${phase} episode ${episode} start ${start}`]);
  }));
  sel.textContent = "";
  keys.forEach(([k, text]) => { const o = el("option", text); o.value = k; sel.appendChild(o); });
  if (!keys.some(([k]) => k === episodeKey)) {
    const learning = keys.filter(([k]) => k.includes("|learning|"));
    episodeKey = keys.length ? (learning.length ? learning[learning.length - 1][0] : keys[0][0]) : null;
  }
  if (episodeKey) sel.value = episodeKey;
}

async function loadEpisode() {
  if (!episodeKey) { drawEpisode(null, null); return; }
  const [run, learner, seed, phase, episode, start] = episodeKey.split("|");
  const q = new URLSearchParams({ run, learner, seed, phase, episode, start });
  const r = await fetch(`/api/episode?${q}`);
  drawEpisode(state.runs[Number(run)], r.ok ? await r.json() : null);
}

function objectiveJobs(runs) {
  const sel = document.getElementById("objective-job");
  const jobs = [];
  runs.forEach((run) => (run.jobs || []).forEach((job) => {
    if (job.objectives) jobs.push([`${run.index}|${job.learner}|${job.seed}`, job, `${runs.length > 1 ? run.name + ": " : ""}${job.learner} s${job.seed}`]);
  }));
  sel.textContent = "";
  jobs.forEach(([k, , text]) => { const o = el("option", text); o.value = k; sel.appendChild(o); });
  if (!jobs.some(([k]) => k === objectiveKey)) {
    const mobo = jobs.find(([, job]) => job.learner === "mobo");
    objectiveKey = mobo ? mobo[0] : (jobs.length ? jobs[0][0] : null);
  }
  if (objectiveKey) sel.value = objectiveKey;
  const hit = jobs.find(([k]) => k === objectiveKey);
  drawObjectives(hit ? hit[1] : null);
}

function statusOf(runs) {
  const t = runs.find((r) => r.tuner && r.tuner.status);
  return t ? t.tuner.status : null;
}

// Each part of the page, timed (window.renderTimes: milliseconds by part, last drawing).
async function render() {
  const runs = state.runs, times = {};
  const timed = async (name, fn) => { const t = performance.now(); await fn(); times[name] = Math.round(performance.now() - t); };
  await timed("tables", () => { drawMessages(runs); drawJobs(runs); drawTuner(runs); drawChanges(runs); });
  await timed("performance", () => drawPerformance(runs, perSeed()));
  await timed("identified", () => drawIdentified(runs, statusOf(runs), perSeed()));
  await timed("objectives", () => objectiveJobs(runs));
  await timed("episode", async () => { trajectoryOptions(runs); await loadEpisode(); });
  window.renderTimes = times;
  document.body.dataset.version = state.version;
  document.getElementById("updated").textContent = `updated ${new Date().toLocaleTimeString()}`;
}

async function poll() {
  try {
    const r = await fetch(`/api/state?since=${state.version || ""}`, { cache: "no-store" });
    const got = await r.json();
    if (got.runs) { state = got; await render(); }
    if (!document.body.dataset.ready) {
      document.body.dataset.readyMs = performance.now().toFixed(0);
      document.body.dataset.ready = "1";
    }
  } catch (err) {
    document.getElementById("updated").textContent = `the server does not answer (${err})`;
  }
  setTimeout(poll, POLL_MS);
}

let resizing = null;
window.addEventListener("resize", () => { clearTimeout(resizing); resizing = setTimeout(render, 300); });

function perSeed() { return document.getElementById("per-seed").checked; }

document.getElementById("per-seed").addEventListener("change", () => {
  drawPerformance(state.runs, perSeed());
  drawIdentified(state.runs, statusOf(state.runs), perSeed());
});
document.getElementById("trajectory").addEventListener("change", (e) => { episodeKey = e.target.value; loadEpisode(); });
document.getElementById("objective-job").addEventListener("change", (e) => { objectiveKey = e.target.value; objectiveJobs(state.runs); });
poll();
