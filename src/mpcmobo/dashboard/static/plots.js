// The figures of the dashboard, drawn with plotly.js (served by the package).
"use strict";

const PALETTE = ["rgb(31,119,180)", "rgb(214,39,40)", "rgb(44,160,44)", "rgb(148,103,189)", "rgb(255,127,14)", "rgb(140,86,75)",
  "rgb(227,119,194)", "rgb(23,190,207)", "rgb(127,127,127)", "rgb(188,189,34)"];
const CONFIG = { displaylogo: false, responsive: true };

function seriesColor(i) { return PALETTE[i % PALETTE.length]; }

function fade(color, alpha) {
  return color.replace("rgb(", "rgba(").replace(")", `,${alpha})`);
}

function label(run, learner, several) { return several ? `${run.name}: ${learner}` : learner; }

// A median line with its min-max band.
function band(x, stats, name, color, dash, group) {
  return [
    { x: x.concat(x.slice().reverse()), y: stats.max.concat(stats.min.slice().reverse()),
      fill: "toself", fillcolor: fade(color, 0.12), line: { width: 0 }, hoverinfo: "skip", mode: "lines",
      showlegend: false, legendgroup: group, type: "scatter", connectgaps: false },
    { x, y: stats.median, name, legendgroup: group, line: { color, dash, width: dash === "dot" ? 1 : 2 },
      type: "scatter", mode: "lines", connectgaps: true },
  ];
}

function levelLines(runs, several) {
  const shapes = [], annotations = [];
  runs.forEach((run) => {
    [["J_star", "J*", "dash"], ["J_initial", "theta0", "dot"]].forEach(([key, text, dash]) => {
      if (run[key] === null || run[key] === undefined) return;
      shapes.push({ type: "line", xref: "paper", x0: 0, x1: 1, y0: run[key], y1: run[key],
        line: { color: "rgb(68,68,68)", width: 1, dash } });
      annotations.push({ xref: "paper", x: 1, y: run[key], xanchor: "right", yanchor: "bottom",
        text: several ? `${text} (${run.name})` : text, showarrow: false, font: { size: 10 } });
    });
  });
  return { shapes, annotations };
}

function changeMarkers(job, name, color, group) {
  const x = [], y = [], text = [];
  job.changes.forEach((c) => {
    const i = job.episode.indexOf(c.episode);
    x.push(c.episode);
    y.push(c.J_eval !== null ? c.J_eval : (i >= 0 ? job.cost[i] : null));
    text.push(describeChange(c));
  });
  return { x, y, text, name: `${name}: deployed theta changed`, legendgroup: group,
    mode: "markers", type: "scatter", hovertemplate: "%{text}<extra></extra>",
    marker: { symbol: "triangle-up", size: 10, color, line: { color: "rgb(0,0,0)", width: 1 } } };
}

function describeChange(c) {
  const parts = [`after episode ${c.episode}`];
  if (c.new_runs) parts.push(`new theta: ${c.new_runs} episodes, mean cost ${fmt(c.new_cost)}`);
  if (c.old_runs) parts.push(`old theta: ${c.old_runs} episodes, mean cost ${fmt(c.old_cost)}`);
  if (c.J_eval !== null) parts.push(`J_eval ${fmt(c.J_eval)}`);
  return parts.join("<br>");
}

function fmt(v, digits = 4) {
  if (v === null || v === undefined) return "";
  if (typeof v !== "number") return String(v);
  return Math.abs(v) >= 1e7 || (Math.abs(v) < 1e-3 && v !== 0) ? v.toExponential(3)
    : Number(v.toPrecision(digits)).toString();
}

function performanceTraces(runs, perSeed) {
  const perf = [], cum = [];
  const several = runs.length > 1;
  let k = 0;
  runs.forEach((run) => {
    (run.learners || []).forEach((learner) => {
      const jobs = (run.jobs || []).filter((j) => j.learner === learner);
      if (!jobs.length) return;
      const color = seriesColor(k++), name = label(run, learner, several), group = name;
      if (perSeed || jobs.length === 1) {
        jobs.forEach((job, s) => {
          const n = jobs.length > 1 ? `${name} s${job.seed}` : name;
          perf.push({ x: job.episode, y: job.cost, name: `${n}: plant cost`, legendgroup: group,
            type: "scatter", mode: "lines", line: { color: fade(color, 0.45), width: 1 },
            meta: { run: run.index, learner, seed: job.seed, kind: "cost" } });
          perf.push({ x: job.episode, y: job.J_eval, name: `${n}: J_eval deployed`,
            legendgroup: group, type: "scatter", mode: "lines+markers", connectgaps: true,
            line: { color, width: 2 }, marker: { size: 4 },
            meta: { run: run.index, learner, seed: job.seed, kind: "J_eval" } });
          perf.push(changeMarkers(job, n, color, group));
          cum.push({ x: job.episode, y: job.cum_cost, name: n, type: "scatter", mode: "lines",
            line: { color }, meta: { run: run.index, learner, seed: job.seed, kind: "cum" } });
        });
      } else {
        const g = run.groups[learner];
        perf.push(...band(g.episode, g.cost, `${name}: plant cost (median)`, color, "dot", group));
        perf.push(...band(g.episode, g.J_eval, `${name}: J_eval deployed (median, ${g.seeds} seeds)`, color, "solid", group));
        cum.push(...band(g.episode, g.cum_cost, `${name} (median, ${g.seeds} seeds)`, color, "solid", name));
      }
    });
  });
  return { perf, cum };
}

function drawPerformance(runs, perSeed) {
  const { perf, cum } = performanceTraces(runs, perSeed);
  const levels = levelLines(runs, runs.length > 1);
  Plotly.react("perf", perf, { margin: { t: 20, r: 10, b: 40, l: 60 },
    xaxis: { title: { text: "episode" } }, yaxis: { title: { text: "mean stage cost" } },
    shapes: levels.shapes, annotations: levels.annotations, legend: { font: { size: 10 } } }, CONFIG);
  Plotly.react("cum", cum, { margin: { t: 20, r: 10, b: 40, l: 60 },
    xaxis: { title: { text: "episode" } }, yaxis: { title: { text: "cumulative plant cost" } },
    legend: { font: { size: 10 } } }, CONFIG);
}

// Panels of one figure (one plotly figure is much cheaper to draw than several): a grid of
// `columns`, each panel {traces, title, levels: [[y, dash]], xtitle}.
function panels(id, list, columns, height) {
  const rows = Math.max(1, Math.ceil(list.length / columns));
  const traces = [], shapes = [], annotations = [];
  const layout = { grid: { rows, columns, pattern: "independent", ygap: 0.35 }, showlegend: false,
    margin: { t: 30, r: 10, b: 30, l: 60 }, height: rows * height };
  list.forEach((p, i) => {
    const n = i ? String(i + 1) : "";
    p.traces.forEach((t) => traces.push({ ...t, xaxis: `x${n}`, yaxis: `y${n}` }));
    (p.levels || []).forEach(([y, dash, color]) => {
      if (y !== null && y !== undefined) shapes.push({ type: "line", xref: `x${n} domain`, x0: 0, x1: 1,
        yref: `y${n}`, y0: y, y1: y, line: { color: color || "rgb(68,68,68)", width: 1, dash } });
    });
    annotations.push({ text: p.title, xref: `x${n} domain`, yref: `y${n} domain`, x: 0.5, y: 1.02,
      xanchor: "center", yanchor: "bottom", showarrow: false, font: { size: 12 } });
    layout[`xaxis${n}`] = { title: { text: p.xtitle, standoff: 2 } };
  });
  layout.shapes = shapes;
  layout.annotations = annotations;
  const div = document.getElementById(id);
  div.style.height = `${layout.height}px`;
  Plotly.react(div, traces, layout, CONFIG);
}

function drawEpisode(run, traj) {
  const div = document.getElementById("episode");
  const sys = run && run.system;
  if (!sys || !traj) { Plotly.purge(div); div.textContent = traj === null ? "no stored trajectory" : ""; return; }
  const dt = sys.dt || 1, list = [];
  const add = (name, y, lb, ub, ref, step) => list.push({ title: `${name} (limits dashed red)`, xtitle: "t",
    traces: [{ x: y.map((_, k) => k * dt), y, name, type: "scatter", mode: "lines",
      line: { shape: step ? "hv" : "linear", color: PALETTE[0] } }],
    levels: [[lb, "dash", "rgb(204,0,0)"], [ub, "dash", "rgb(204,0,0)"], [ref, "dot", "rgb(136,136,136)"]] });
  sys.state_names.forEach((n, i) => add(n, traj.x[i], sys.x_lb[i], sys.x_ub[i], sys.x_ref[i], false));
  sys.input_names.forEach((n, i) => add(n, traj.u[i], sys.u_lb[i], sys.u_ub[i], sys.u_ref[i], true));
  panels("episode", list, 3, 240);
}

// The median and min-max of several series by index (null where no series has a value).
function medianBand(series) {
  const n = Math.max(...series.map((s) => s.length));
  const out = { x: [], median: [], min: [], max: [] };
  for (let i = 0; i < n; i++) {
    const v = series.map((s) => s[i]).filter((y) => y !== null && y !== undefined).sort((a, b) => a - b);
    out.x.push(i);
    out.median.push(v.length ? (v[(v.length - 1) >> 1] + v[v.length >> 1]) / 2 : null);
    out.min.push(v.length ? v[0] : null);
    out.max.push(v.length ? v[v.length - 1] : null);
  }
  return out;
}

function drawIdentified(runs, status, perSeed) {
  const shown = runs.filter((r) => r.identified);
  document.getElementById("identified-section").hidden = !shown.length;
  if (!shown.length) return;
  const list = [];
  shown.forEach((run) => {
    run.identified.names.forEach((name, p) => {
      const traces = [];
      run.learners.forEach((learner, l) => {
        const jobs = run.jobs.filter((j) => j.learner === learner && j.identified.length);
        if (perSeed || jobs.length === 1) {
          jobs.forEach((job) => traces.push({ x: job.episode, y: job.identified[p], type: "scatter",
            mode: "lines", name: `${learner} s${job.seed}`, line: { color: seriesColor(l) } }));
        } else if (jobs.length) {
          const m = medianBand(jobs.map((j) => j.identified[p]));
          traces.push(...band(m.x, m, `${learner} (median, ${jobs.length} seeds)`, seriesColor(l), "solid", learner));
        }
      });
      const fit = status && status.identification && status.identification.parameters
        && status.identification.parameters[name];
      if (fit && fit.std !== null && run.jobs.length) {
        const last = run.jobs[0].episode[run.jobs[0].episode.length - 1];
        traces.push({ x: [last], y: [fit.estimate], type: "scatter", mode: "markers",
          name: "last fit +- 2 std", error_y: { type: "data", array: [2 * fit.std], visible: true } });
      }
      list.push({ title: `${name}${runs.length > 1 ? " (" + run.name + ")" : ""}: nominal dashed, true dotted`,
        xtitle: "episode", traces,
        levels: [[run.identified.nominal[p], "dash"], [run.identified.true[p], "dot"]] });
    });
  });
  panels("identified", list, 3, 240);
}

// f2, f3 and f4 against f1 (SVG scatter: no WebGL), the Pareto front's episodes in red.
function drawObjectives(job) {
  document.getElementById("objectives-section").hidden = !job;
  if (!job) return;
  const [f1, ...others] = job.objectives.values;
  const front = new Set(job.objectives.front);
  const text = job.episode.map((e) => `episode ${e}`);
  const onFront = (values, yes) => values.map((v, i) => (front.has(i) === yes ? v : null));
  const traces = [], layout = { margin: { t: 30, r: 10, b: 40, l: 60 }, showlegend: true,
    grid: { rows: 1, columns: 3, pattern: "independent" }, legend: { orientation: "h", y: -0.2 },
    title: { text: `Pareto front of f1..f4: ${front.size} of ${job.episode.length} episodes`, font: { size: 12 } } };
  others.forEach((fk, k) => {
    const axis = k ? String(k + 1) : "";
    [[false, "rgb(154,167,181)", 5, "observations"], [true, "rgb(214,39,40)", 9, "Pareto front"]].forEach(([yes, color, size, name]) => {
      traces.push({ x: onFront(f1, yes), y: onFront(fk, yes), text, type: "scatter", mode: "markers",
        xaxis: `x${axis}`, yaxis: `y${axis}`, name, legendgroup: name, showlegend: k === 0,
        marker: { color, size }, hovertemplate: "%{text}<br>f1 %{x}<br>%{y}<extra></extra>" });
    });
    layout[`xaxis${axis}`] = { title: { text: "f1" } };
    layout[`yaxis${axis}`] = { title: { text: `f${k + 2}` } };
  });
  Plotly.react("objectives", traces, layout, CONFIG);
}
