// The figures of the dashboard, drawn with uPlot (served by the package, canvas: no WebGL).
// Every chart is kept in window.charts[id] (its data and series: what the tests read).
"use strict";

const PALETTE = ["rgb(31,119,180)", "rgb(214,39,40)", "rgb(44,160,44)", "rgb(148,103,189)",
  "rgb(255,127,14)", "rgb(140,86,75)", "rgb(227,119,194)", "rgb(23,190,207)",
  "rgb(127,127,127)", "rgb(188,189,34)"];
const GREY = "rgb(68,68,68)", RED = "rgb(204,0,0)", LIGHT = "rgb(136,136,136)";
window.charts = {};

function seriesColor(i) { return PALETTE[i % PALETTE.length]; }
function fade(color, alpha) { return color.replace("rgb(", "rgba(").replace(")", `,${alpha})`); }
function label(run, learner, several) { return several ? `${run.name}: ${learner}` : learner; }

function fmt(v, digits = 4) {
  if (v === null || v === undefined) return "";
  if (typeof v !== "number") return String(v);
  return Math.abs(v) >= 1e7 || (Math.abs(v) < 1e-3 && v !== 0) ? v.toExponential(3)
    : Number(v.toPrecision(digits)).toString();
}

// Horizontal lines [{y, dash, color, text}] drawn over a chart (limits, J*, theta0's level).
// Each line's text sits at the right end, above the line; a text that would cover one drawn
// before goes below its line, else to the left of the texts in its way. The placed boxes are
// kept in u.levelLabels [{text, left, top, right, bottom}] (canvas pixels).
function levelsHook(levels) {
  return (u) => {
    const ctx = u.ctx, { left, width } = u.bbox;
    ctx.save();
    ctx.font = `${11 * devicePixelRatio}px sans-serif`;
    ctx.textAlign = "right";
    const placed = [];
    levels.forEach((l) => {
      if (l.y === null || l.y === undefined) return;
      const y = Math.round(u.valToPos(l.y, "y", true));
      ctx.strokeStyle = l.color || GREY;
      ctx.lineWidth = 1;
      ctx.setLineDash(l.dash === "dot" ? [2, 3] : [6, 4]);
      ctx.beginPath(); ctx.moveTo(left, y); ctx.lineTo(left + width, y); ctx.stroke();
      if (l.text) {
        const box = labelBox(ctx, l.text, left + width - 4, y, placed);
        ctx.fillStyle = l.color || GREY;
        ctx.fillText(l.text, box.right, box.bottom - 2 * devicePixelRatio);
        placed.push(box);
      }
    });
    ctx.restore();
    u.levelLabels = placed;
  };
}

// Where a level's text goes (levelsHook): the first of above its line, below it, and the
// same further left, whose box overlaps none of the boxes `placed`.
function labelBox(ctx, text, right, y, placed) {
  const w = ctx.measureText(text).width, h = 13 * devicePixelRatio, gap = 2 * devicePixelRatio;
  const box = (r, bottom) => ({ text, left: r - w, top: bottom - h, right: r, bottom });
  const clear = (b) => placed.every((o) =>
    b.right <= o.left || b.left >= o.right || b.bottom <= o.top || b.top >= o.bottom);
  let r = right;
  for (let i = 0; i <= placed.length; i += 1) {
    for (const b of [box(r, y - gap), box(r, y + h + gap)]) if (clear(b)) return b;
    const inWay = placed.filter((o) => o.right > r - w && o.left < r);
    r = Math.min(...inWay.map((o) => o.left), r) - 8 * devicePixelRatio;
  }
  return box(r, y - gap);
}

// A y range that holds the data and the levels.
function rangeWith(levels) {
  return (u, min, max) => {
    const ys = levels.map((l) => l.y).filter((y) => y !== null && y !== undefined);
    let lo = Math.min(min ?? Infinity, ...ys), hi = Math.max(max ?? -Infinity, ...ys);
    if (!isFinite(lo) || !isFinite(hi)) return [0, 1];
    const pad = (hi - lo || Math.abs(hi) || 1) * 0.05;
    return [lo - pad, hi + pad];
  };
}

// the episode axis's tick steps: whole episodes only
const EPISODE_TICKS = [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000];

// One chart in the element `id` (replacing the one there): x and series [{label, y, ...}].
function chart(id, { x, series, levels = [], xlabel = "", ylabel = "", title = "", height = 300,
  bands = [], legend = true, parent = null }) {
  let el = document.getElementById(id);
  if (!el) { el = document.createElement("div"); el.id = id; el.className = "panel"; parent.appendChild(el); }
  if (window.charts[id]) window.charts[id].destroy();
  el.textContent = "";
  const width = Math.max(300, el.clientWidth || el.parentElement.clientWidth || 600);
  const opts = { title, width, height, legend: { show: legend, live: legend },
    scales: { x: { time: false }, y: { range: rangeWith(levels) } },
    axes: [{ label: xlabel, size: 40, incrs: xlabel === "episode" ? EPISODE_TICKS : undefined },
      { label: ylabel, size: 60 }],
    series: [{ label: xlabel || "x" }, ...series.map(({ y, edge, ...s }) => ({ spanGaps: true, ...s }))],
    bands, hooks: { draw: [levelsHook(levels)] }, cursor: { drag: { x: true, y: false } } };
  const u = new uPlot(opts, [x, ...series.map((s) => s.y)], el);
  u.levels = levels;
  if (legend) {  // the bands' edges have no entry of their own
    const rows = u.root.querySelectorAll(".u-legend .u-series");
    series.forEach((s, i) => { if (s.edge && rows[i + 1]) rows[i + 1].style.display = "none"; });
  }
  window.charts[id] = u;
  return u;
}

// Series of one job aligned on the episodes 0..n-1 (null where the job has none).
function aligned(job, values, n) {
  const out = new Array(n).fill(null);
  job.episode.forEach((e, i) => { if (e < n) out[e] = values[i]; });
  return out;
}

function levelLines(runs) {
  const levels = [];
  runs.forEach((run) => {
    const who = runs.length > 1 ? ` (${run.name})` : "";
    levels.push({ y: run.J_star, dash: "dash", text: `J*${who}` });
    levels.push({ y: run.J_initial, dash: "dot", text: `theta0${who}` });
  });
  return levels;
}

function describeChange(c) {
  const parts = [`after episode ${c.episode}`];
  if (c.new_runs) parts.push(`new theta: ${c.new_runs} episodes, mean cost ${fmt(c.new_cost)}`);
  if (c.old_runs) parts.push(`old theta: ${c.old_runs} episodes, mean cost ${fmt(c.old_cost)}`);
  return parts.join("; ");
}

const NO_LINE = () => null;

// The band [max, min] of a median series, as uPlot series and a band between them.
function withBand(list, bands, stats, name, color, dash) {
  const base = list.length + 1;
  list.push({ label: `${name} max`, y: stats.max, stroke: "transparent", points: { show: false }, edge: true });
  list.push({ label: `${name} min`, y: stats.min, stroke: "transparent", points: { show: false }, edge: true });
  list.push({ label: name, y: stats.median, stroke: color, width: dash === "dot" ? 1 : 2,
    dash: dash === "dot" ? [2, 3] : undefined, points: { show: false } });
  bands.push({ series: [base, base + 1], fill: fade(color, 0.15) });
}

function drawPerformance(runs, perSeed) {
  const n = Math.max(1, ...runs.flatMap((r) => (r.jobs || []).map((j) => Math.max(0, ...j.episode) + 1)));
  const x = Array.from({ length: n }, (_, i) => i);
  const perf = [], cum = [], perfBands = [], cumBands = [];
  let k = 0;
  runs.forEach((run) => (run.learners || []).forEach((learner) => {
    const jobs = (run.jobs || []).filter((j) => j.learner === learner);
    if (!jobs.length) return;
    const color = seriesColor(k++), name = label(run, learner, runs.length > 1);
    if (perSeed || jobs.length === 1) {
      jobs.forEach((job) => {
        const who = jobs.length > 1 ? `${name} s${job.seed}` : name;
        perf.push({ label: `${who}: plant cost`, y: aligned(job, job.cost, n), stroke: fade(color, 0.45), width: 1, points: { show: false } });
        // held until the next evaluation, as the median view holds it: not a slope between them
        perf.push({ label: `${who}: J_eval deployed`, y: aligned(job, job.J_eval, n), stroke: color, width: 2, points: { show: true, size: 4 },
          paths: uPlot.paths.stepped({ align: 1 }) });
        const marks = new Array(n).fill(null);
        job.changes.forEach((c) => { if (c.episode < n) marks[c.episode] = c.J_eval !== null ? c.J_eval : job.cost[job.episode.indexOf(c.episode)]; });
        perf.push({ label: `${who}: deployed theta changed`, y: marks, stroke: color, paths: NO_LINE, points: { show: true, size: 10, fill: color } });
        cum.push({ label: who, y: aligned(job, job.cum_cost, n), stroke: color, width: 2, points: { show: false } });
      });
    } else {
      const g = run.groups[learner];
      const pad = (s) => ({ median: s.median.concat(new Array(n - s.median.length).fill(null)),
        min: s.min.concat(new Array(n - s.min.length).fill(null)), max: s.max.concat(new Array(n - s.max.length).fill(null)) });
      withBand(perf, perfBands, pad(g.cost), `${name}: plant cost (median, ${g.seeds} seeds)`, color, "dot");
      withBand(perf, perfBands, pad(g.J_eval), `${name}: J_eval deployed (median, ${g.seeds} seeds)`, color, "solid");
      withBand(cum, cumBands, pad(g.cum_cost), `${name} (median, ${g.seeds} seeds)`, color, "solid");
    }
  }));
  chart("perf", { x, series: perf, bands: perfBands, levels: levelLines(runs), xlabel: "episode", ylabel: "mean stage cost", height: 360 });
  chart("cum", { x, series: cum, bands: cumBands, xlabel: "episode", ylabel: "cumulative plant cost", height: 260 });
}

function drawEpisode(run, traj) {
  const parent = document.getElementById("episode");
  const sys = run && run.system;
  if (!sys || !traj) {
    Object.keys(window.charts).filter((k) => k.startsWith("episode-")).forEach((k) => { window.charts[k].destroy(); delete window.charts[k]; });
    parent.textContent = traj === null ? "no stored trajectory" : "";
    return;
  }
  if (!parent.querySelector(".panel")) parent.textContent = "";
  const dt = sys.dt || 1;
  const panel = (key, name, y, lb, ub, ref, step) => chart(`episode-${key}`, { parent,
    x: y.map((_, i) => i * dt), title: `${name} (limits dashed red)`, xlabel: "t", height: 220, legend: false,
    series: [{ label: name, y, stroke: PALETTE[0], width: 2, points: { show: false },
      paths: step ? uPlot.paths.stepped({ align: 1 }) : undefined }],
    levels: [{ y: lb, color: RED }, { y: ub, color: RED }, { y: ref, color: LIGHT, dash: "dot" }] });
  sys.state_names.forEach((n, i) => panel(`x_${n}`, n, traj.x[i], sys.x_lb[i], sys.x_ub[i], sys.x_ref[i], false));
  sys.input_names.forEach((n, i) => panel(`u_${n}`, n, traj.u[i], sys.u_lb[i], sys.u_ub[i], sys.u_ref[i], true));
}

// The median and min-max of several series by index (null where no series has a value).
function medianBand(series) {
  const n = Math.max(...series.map((s) => s.length));
  const out = { median: [], min: [], max: [] };
  for (let i = 0; i < n; i++) {
    const v = series.map((s) => s[i]).filter((y) => y !== null && y !== undefined).sort((a, b) => a - b);
    out.median.push(v.length ? (v[(v.length - 1) >> 1] + v[v.length >> 1]) / 2 : null);
    out.min.push(v.length ? v[0] : null);
    out.max.push(v.length ? v[v.length - 1] : null);
  }
  return out;
}

function drawIdentified(runs, status, perSeed) {
  const parent = document.getElementById("identified");
  const shown = runs.filter((r) => r.identified);
  document.getElementById("identified-section").hidden = !shown.length;
  shown.forEach((run) => run.identified.names.forEach((name, p) => {
    const n = Math.max(1, ...run.jobs.map((j) => Math.max(0, ...j.episode) + 1));
    const series = [], bands = [];
    run.learners.forEach((learner, l) => {
      const jobs = run.jobs.filter((j) => j.learner === learner && j.identified.length);
      if (perSeed || jobs.length === 1) {
        jobs.forEach((job) => series.push({ label: `${learner} s${job.seed}`, y: aligned(job, job.identified[p], n),
          stroke: seriesColor(l), width: 1.5, points: { show: false } }));
      } else if (jobs.length) {
        withBand(series, bands, medianBand(jobs.map((j) => aligned(j, j.identified[p], n))),
          `${learner} (median, ${jobs.length} seeds)`, seriesColor(l), "solid");
      }
    });
    const fit = status && status.identification && status.identification.parameters
      && status.identification.parameters[name];
    const levels = [{ y: run.identified.nominal[p], text: "nominal" }, { y: run.identified.true[p], dash: "dot", text: "true" }];
    if (fit && fit.std !== null && fit.std !== undefined) {
      levels.push({ y: fit.estimate + 2 * fit.std, color: LIGHT, dash: "dot", text: "last fit + 2 std" });
      levels.push({ y: fit.estimate - 2 * fit.std, color: LIGHT, dash: "dot", text: "last fit - 2 std" });
    }
    chart(`identified-${run.index}-${p}`, { parent, x: Array.from({ length: n }, (_, i) => i), series, bands, levels,
      title: `${name}${runs.length > 1 ? " (" + run.name + ")" : ""}`, xlabel: "episode", height: 220, legend: false });
  }));
}

// f2, f3 and f4 against f1, the Pareto front's episodes in red.
function drawObjectives(job) {
  document.getElementById("objectives-section").hidden = !job;
  const parent = document.getElementById("objectives");
  if (!job) return;
  const [f1, ...others] = job.objectives.values;
  const front = new Set(job.objectives.front);
  const order = f1.map((v, i) => i).filter((i) => f1[i] !== null).sort((a, b) => f1[a] - f1[b]);
  document.getElementById("objectives-title").textContent =
    `${job.learner} s${job.seed}: ${front.size} of ${job.episode.length} episodes on the Pareto front`;
  others.forEach((fk, k) => chart(`objectives-f${k + 2}`, { parent, x: order.map((i) => f1[i]),
    title: `f${k + 2} against f1`, xlabel: "f1", height: 260, legend: false, series: [
      { label: "observations", y: order.map((i) => (front.has(i) ? null : fk[i])), stroke: LIGHT, paths: NO_LINE, points: { show: true, size: 5, fill: LIGHT } },
      { label: "Pareto front", y: order.map((i) => (front.has(i) ? fk[i] : null)), stroke: RED, paths: NO_LINE, points: { show: true, size: 8, fill: RED } }] }));
}
