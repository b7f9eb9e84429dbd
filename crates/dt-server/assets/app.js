// shocktwin dashboard: the fleet sorted by risk, and for the selected asset its live
// pressure (Server-Sent Events), its leak trend with the predicted crossings, its recent
// runs and health changes. Plain ES2020, no build step; charts by the vendored uPlot.
// Every URL is relative so that the page works behind a path prefix.
"use strict";

const $ = (id) => document.getElementById(id);
const DASH = "–";
const DAY_S = 86400;
const MAX_LIVE = 3000;           // points kept in the live chart (~60 s at 50 Hz)
const LIVE_SILENT_MS = 30000;    // the live chart keeps to its run until it ends or is silent this long
const OTHER_NOTE_MS = 3000;      // "another run streams too" while it sent this recently
const REFRESH_MS = 5000;         // fleet poll
const HEALTH_RANK = { leak: 0, low: 1, unknown: 2, ok: 3 };
const COLORS = { p: "#2b6cb0", band: "rgba(43,108,176,0.16)", warn: "#b7791f", fault: "#c0392b", fit: "#1d232b" };

const S = {
  assets: new Map(),             // asset_id -> row of GET v1/assets (updated live)
  selected: null,
  live: { x: [], p: [], lo: [], hi: [] },
  liveCount: 0, lastEvent: null, seeded: false,
  fleetDirty: false, fleetDrawn: 0, liveDirty: false, detailTimer: null, refreshTimer: null,
  liveChart: null, trendChart: null, trendKey: null,
  uploads: new Set(),            // run ids of uploads (inbox, POST v1/runs) seen starting
  // The processing of a run (`seq` of the events) the live chart draws, its run id, and when it
  // last sent (ms; 0: ended); another one of the asset streaming meanwhile, not drawn.
  liveSeq: null, liveRunId: null, liveRunAt: 0,
  otherSeq: null, otherRunId: null, otherRunAt: 0,
};

// ---- formatting --------------------------------------------------------------------
const esc = (s) => String(s).replace(/[&<>"']/g, (c) => `&#${c.charCodeAt(0)};`);
const fin = (v) => typeof v === "number" && Number.isFinite(v);
const num = (v, d = 2) => (fin(v) ? v.toFixed(d).replace(/^-(0\.?0*)$/, "$1") : DASH);   // no "-0.00"
// The |ÿ_r| range a baseline reading was read at, as its tooltip says it ("" when unknown).
const excitation = (range) => (Array.isArray(range) ? ` (|ÿ| ${num(range[0], 2)}–${num(range[1], 2)} m/s²)` : "");
const tsec = (iso) => (iso ? Date.parse(iso) / 1000 : null);   // RFC 3339 -> Unix s
const iso = (s) => new Date(s * 1000).toISOString();
const fmtDate = (s) => (fin(s) ? iso(s).slice(0, 10) : DASH);
const fmtTime = (s) => (fin(s) ? iso(s).slice(0, 19).replace("T", " ") : DASH);
function ago(ms) {
  if (!fin(ms) || ms <= 0) return DASH;
  const s = Math.max(0, (Date.now() - ms) / 1000);
  if (s < 60) return `${Math.round(s)} s ago`;
  if (s < 3600) return `${Math.round(s / 60)} min ago`;
  if (s < DAY_S) return `${(s / 3600).toFixed(1)} h ago`;
  return `${(s / DAY_S).toFixed(1)} d ago`;
}
function duration(t0, t1) {
  if (!fin(t0) || !fin(t1)) return DASH;
  const s = t1 - t0;
  return s < 120 ? `${s.toFixed(0)} s` : s < 7200 ? `${(s / 60).toFixed(1)} min` : `${(s / 3600).toFixed(1)} h`;
}
// A run whose log says it is simulated (its metadata's `simulated` key), marked one by one:
// a fleet may mix simulated runs with real ones.
const simPill = (simulated, text = "simulated") => simulated === true
  ? ` <span class="pill sim" title="the log says it is simulated (its metadata's simulated key): not a measurement of a real damper">${text}</span>`
  : "";
// `unknown` says why in its tooltip (a helper's trial: most of a fleet without baselines is a
// grey UNKNOWN, and nothing said why)
const BADGE_TITLE = {
  unknown: "no verdict: not excited yet, or the 95 % interval reaches across a threshold " +
    "(a unit baseline, read at a known charge, narrows it)",
  leak: "the 95 % interval lies below the fault threshold",
  low: "the 95 % interval lies below the warn threshold",
  ok: "the 95 % interval lies above the warn threshold",
};
const badge = (h) => `<span class="badge ${esc(h || "unknown")}" title="${BADGE_TITLE[h || "unknown"] || ""}">${esc(h || "unknown")}</span>`;

// With bearer tokens on (docs/daemon.md, "Exposing the daemon"), open the dashboard as
// /#token=<read token>: the fragment never reaches the server or its logs; it is kept in
// this tab's sessionStorage and removed from the address bar.
const TOKEN = (() => {
  const m = /(?:^#|&)token=([^&]+)/.exec(location.hash);
  if (m) {
    sessionStorage.setItem("shocktwin-token", decodeURIComponent(m[1]));
    history.replaceState(null, "", location.pathname + location.search);
  }
  return sessionStorage.getItem("shocktwin-token");
})();

// A request that never reached the daemon (it is down, the network is): said as such, and
// told apart from an error of this page's own code (a review: a TypeError of ours read
// "the daemon does not answer").
class Unreachable extends Error {}
async function getJSON(path) {
  const headers = TOKEN ? { Authorization: `Bearer ${TOKEN}` } : {};
  let r;
  try {
    r = await fetch(path, { cache: "no-store", headers });
  } catch (err) {
    throw new Unreachable(`${path}: ${err.message || err}`);
  }
  if (r.status === 401) throw new Error(`${path}: 401 — this daemon needs a read token: open /#token=<token>`);
  if (!r.ok) {
    let msg = r.statusText;
    try { msg = (await r.json()).error || msg; } catch (_) { /* not JSON */ }
    throw new Error(`${path}: ${r.status} ${msg}`);
  }
  return r.json();
}
function showError(el, err) {
  el.hidden = !err;
  el.textContent = err ? String(err.message || err) : "";
}

// ---- fleet table -------------------------------------------------------------------
function riskOrder(a, b) {
  const h = (HEALTH_RANK[a.health] ?? 2) - (HEALTH_RANK[b.health] ?? 2);
  if (h) return h;
  // by the predicted crossing's date, as the column shows it (`days_to_fault` counts from each
  // asset's own last run; a review)
  const da = tsec(a.trend?.fault?.t), db = tsec(b.trend?.fault?.t);
  if (fin(da) !== fin(db)) return fin(da) ? -1 : 1;   // null last
  if (fin(da) && da !== db) return da - db;
  return a.asset_id.localeCompare(b.asset_id);
}

// A bar from 0 to a scale covering the nominal pressure: the 95 % interval, the estimate
// and the warn/fault marks.
function pressureCell(a) {
  const max = Math.max(15, (fin(a.expected_bar) ? a.expected_bar : 12) * 1.25);
  const pct = (v) => `${(100 * Math.min(Math.max(v, 0), max) / max).toFixed(1)}%`;
  const p = fin(a.pressure_avg_bar) ? a.pressure_avg_bar : a.pressure_bar;
  let bar = "";
  if (fin(p)) bar += `<span class="fill" style="width:${pct(p)}"></span>`;
  if (fin(a.pressure_lo_bar) && fin(a.pressure_hi_bar)) {
    bar += `<span class="iv" style="left:${pct(a.pressure_lo_bar)};width:calc(${pct(a.pressure_hi_bar)} - ${pct(a.pressure_lo_bar)})"></span>`;
  }
  if (fin(p)) bar += `<span class="pt" style="left:${pct(p)}"></span>`;
  if (fin(a.warn_bar)) bar += `<span class="th warn" style="left:${pct(a.warn_bar)}" title="warn ${a.warn_bar} bar"></span>`;
  if (fin(a.fault_bar)) bar += `<span class="th fault" style="left:${pct(a.fault_bar)}" title="fault ${a.fault_bar} bar"></span>`;
  const iv = fin(a.pressure_lo_bar) && fin(a.pressure_hi_bar)
    ? `[${num(a.pressure_lo_bar)}, ${num(a.pressure_hi_bar)}]` : "";
  return `<span class="pbar">${bar}</span><span class="num">${num(p)}</span> <span class="small">${iv}</span>`;
}

function leakCell(t) {
  if (!t || t.status !== "ok" || !fin(t.leak_rate_bar_per_day)) {
    return `<span class="small" title="${esc(t?.reason || "no trend yet")}">${DASH}</span>`;
  }
  const half = fin(t.leak_rate_lo_bar_per_day) && fin(t.leak_rate_hi_bar_per_day)
    ? ` ± ${num((t.leak_rate_hi_bar_per_day - t.leak_rate_lo_bar_per_day) / 2, 3)}` : "";
  return `${num(t.leak_rate_bar_per_day, 3)}<span class="small">${half}</span>`;
}

// Days from now to a predicted crossing at `s` (Unix s): the leak goes on between runs, so the
// count is from today, not from the asset's last run (a helper's trial: "in 1.2 d" for a
// crossing long past); one already past says so.
function fromNow(s) {
  if (!fin(s)) return "";
  const d = (s - Date.now() / 1000) / DAY_S, n = Math.abs(d) < 10 ? Math.abs(d).toFixed(1) : Math.abs(d).toFixed(0);
  return d >= 0 ? `in ${n} d` : `<span class="bad">passed ${n} d ago</span>`;
}

function faultCell(t) {
  const c = t?.fault;
  if (c && c.t) {
    const last = fin(t.days_to_fault)
      ? `; ${t.days_to_fault.toFixed(1)} d after the asset's last run` : "";
    return `<span title="predicted crossing of the fault threshold${last}">${fmtDate(tsec(c.t))}</span>` +
      ` <span class="small">${fromNow(tsec(c.t))}</span>`;
  }
  const why = c?.reason || (t && t.status !== "ok" ? t.reason : null);
  return why ? `<span class="small">${esc(why)}</span>` : DASH;
}

function renderFleet() {
  S.fleetDirty = false;
  S.fleetDrawn = Date.now();
  const rows = [...S.assets.values()].sort(riskOrder);
  // the row with the keyboard's focus keeps it through the redraw
  const focused = document.activeElement?.closest?.("#fleet tr[data-asset-id]")?.dataset.assetId;
  $("fleet-empty").hidden = rows.length > 0;
  $("fleet").hidden = rows.length === 0;
  $("fleet").tBodies[0].innerHTML = rows.map((a) => {
    const run = a.active_runs > 0 ? `<span class="pill">● streaming</span>` : "";
    const sim = simPill(a.simulated);
    const b = a.baseline;   // the unit's baseline narrows its interval (read at a known charge)
    const read = b?.kind === "road"
      ? `seal read over ${b.blocks} blocks of drive (offset ${num(b.offset_n, 2)} N) at a known ${num(b.charge_bar, 1)} bar`
      : `read ${num(b?.read_bar, 2)} ± ${num(b?.read_sd_bar, 2)} bar at a known ${num(b?.charge_bar, 1)} bar` +
        excitation(b?.accel_range_mps2) +
        // one reading per excitation: a run is corrected by the nearest
        (b?.other_excitations ?? []).map((o) => `; ${num(o.read_bar, 2)} ± ${num(o.read_sd_bar, 2)} bar at ` +
          `a known ${num(o.charge_bar, 1)} bar${excitation(o.accel_range_mps2)}`).join("");
    const base = b ? ` <span class="pill" title="unit baseline (${esc(b.source)}${b.set_at ? `, ${fmtTime(tsec(b.set_at))} UTC` : ""}): ` +
      `${read}">baseline</span>` : "";
    const road = a.road ? ` <span class="pill road" title="driven on roads: the road observer reads the charge ` +
      `from 10 s blocks of drive (its estimate changes once a block)">road</span>` : "";
    const sv = a.service;   // a service reported at a known charge: the next drive is read into a baseline
    const svc = sv ? ` <span class="pill" title="service at ${num(sv.charge_bar, 1)} bar reported ${fmtTime(tsec(sv.set_at))} UTC: ` +
      `the unit's next drive is read into its baseline${sv.last_refusal ? `; last run: ${esc(sv.last_refusal)}` : ""}">service pending</span>` : "";
    const obs = a.last_run_observer?.not_calibrated_here ? ` <span class="pill bad obs-uncal" title="${esc(observerText(a.last_run_observer))}` +
      `: the estimate kept its prior; calibrate the observer at this excitation (python -m train.observer fit)">observer not calibrated here</span>` : "";
    const rn = a.last_run_road?.why_none ? ` <span class="pill bad road-none" title="${esc(a.last_run_road.why_none)}` +
      `">road: no block read</span>` : "";
    const failed = a.last_run_status && a.last_run_status !== "completed"
      ? ` <span class="small bad" title="${esc(a.last_run_reason || "")}">last run ${esc(a.last_run_status)}</span>` : "";
    // one tab stop in the table (the selected row, else the first): the arrows move between
    // rows, and Tab leaves the table at once however many assets it lists (a review)
    const stop = a.asset_id === S.selected || (!S.assets.has(S.selected) && a === rows[0]);
    return `<tr data-asset-id="${esc(a.asset_id)}" tabindex="${stop ? 0 : -1}" class="${a.asset_id === S.selected ? "sel" : ""}"` +
      `${a.asset_id === S.selected ? ' aria-current="true"' : ""}>
      <td class="id">${esc(a.asset_id)}${sim}${run}${road}${base}${svc}${obs}${rn}</td><td>${badge(a.health)}</td><td>${pressureCell(a)}</td>
      <td>${leakCell(a.trend)}</td><td class="fault">${faultCell(a.trend)}</td>
      <td title="${a.last_update_unix_ms ? iso(a.last_update_unix_ms / 1000) : ""}">${ago(a.last_update_unix_ms)}${failed}</td></tr>`;
  }).join("");
  if (focused) $("fleet").querySelector(`tr[data-asset-id="${CSS.escape(focused)}"]`)?.focus({ preventScroll: true });
}

async function refreshFleet() {
  try {
    const body = await getJSON("v1/assets");
    S.assets = new Map(body.assets.map((a) => [a.asset_id, a]));
    showError($("error"), null);
    $("fleet").classList.remove("stale");
    if (!S.selected && body.assets.length) {
      const wanted = decodeURIComponent(location.hash.slice(1));
      select(wanted || [...S.assets.values()].sort(riskOrder)[0].asset_id);
    } else if (S.selected && S.assets.has(S.selected)) {
      if ($("asset-body").hidden) select(S.selected);   // it was unknown until now
      else loadDetail();
    }
    renderFleet();
  } catch (err) {
    // a network failure says only "Failed to fetch" (a helper's trial): say what it means
    showError($("error"), err instanceof Unreachable
      ? `the daemon does not answer (${err.message}): the table shows what it said last; trying again every ${REFRESH_MS / 1000} s`
      : err);
    $("fleet").classList.toggle("stale", err instanceof Unreachable);
  }
  scheduleRefresh(REFRESH_MS);
}
function scheduleRefresh(ms) {   // one pending poll at most
  clearTimeout(S.refreshTimer);
  S.refreshTimer = setTimeout(refreshFleet, ms);
}

// ---- the selected asset --------------------------------------------------------------
function select(id) {
  if (!id) return;
  S.selected = id;
  history.replaceState(null, "", `#${encodeURIComponent(id)}`);
  S.live = { x: [], p: [], lo: [], hi: [] };
  S.liveSeq = S.otherSeq = null;
  S.seeded = false;
  S.trendKey = null;
  $("asset").hidden = false;
  $("asset-title").textContent = id;
  renderFleet();
  const a = S.assets.get(id);
  $("asset-body").hidden = !a;
  if (!a) {
    showError($("asset-error"), `unknown asset “${id}”: not in the fleet`);
    $("asset-health").outerHTML = `<span id="asset-health"></span>`;
    $("asset-sub").textContent = "";
    return;
  }
  showError($("asset-error"), null);
  headline(a);
  drawLive();
  drawTrend(null);
  loadDetail();
}

function headline(a) {
  $("asset-health").outerHTML = `<span id="asset-health">${badge(a.health)}</span>`;
  $("asset-sub").textContent = `${a.simulated ? "simulated data · " : ""}run ${a.run_id || DASH} · nominal ${num(a.expected_bar, 1)} bar · ` +
    `warn ${num(a.warn_bar, 1)} · fault ${num(a.fault_bar, 1)} bar · ${a.ticks ?? 0} estimates`;
}

// The store's view of the selected asset, on selection and with every fleet poll: its 1 s
// history (the live chart's seed, until it once arrives), its trend with the run points
// (the fleet list carries only a summary), its runs and its health changes. Each part on
// its own, so that one that fails leaves the others shown. The trend is asked for once the
// fleet list shows one (an asset's first trend comes a little after its first run).
async function loadDetail() {
  const id = S.selected, base = `v1/assets/${encodeURIComponent(id)}`;
  const hasTrend = S.assets.get(id)?.trend != null;
  const parts = await Promise.allSettled([
    S.seeded ? null : getJSON(`${base}/history?step_s=1`), hasTrend ? getJSON(`${base}/trend`) : null,
    getJSON(`${base}/runs`), getJSON(`${base}/health`)]);
  if (id !== S.selected) return;   // the user moved on meanwhile
  const [hist, trend, runs, changes] = parts.map((r) => (r.status === "fulfilled" ? r.value : null));
  if (hist) { seedLive(hist.points); S.seeded = true; }
  if (trend || !hasTrend) drawTrend(trend);   // a failed request keeps the chart shown
  if (runs) renderRuns(runs.runs);
  if (changes) renderChanges(changes.changes);
  showError($("asset-error"), parts.find((r) => r.status === "rejected")?.reason);
}
function scheduleDetail() {   // coalesces bursts of run/health events
  clearTimeout(S.detailTimer);
  S.detailTimer = setTimeout(() => S.selected && loadDetail(), 500);
}

// What the charge observer made of a run's velocity reversals (`observer` of /runs, `last_run_observer`).
function observerText(o) {
  if (!o) return "";
  if (!o.detected) return "no reversal: the run did not excite the damper";
  const parts = [`${o.detected} reversals`, `${o.used} read`];
  if (o.spared) parts.push(`${o.spared} spared`);
  if (o.skipped) parts.push(`${o.skipped} failed their window`);
  if (o.rejected) parts.push(`${o.rejected} rejected`);
  if (o.uncalibrated) parts.push(`${o.uncalibrated} at an excitation the calibration does not cover`);
  return parts.join(", ");
}
function observerCell(o) {
  if (!o) return `<td class="small">${DASH}</td>`;
  const text = observerText(o);
  if (o.not_calibrated_here) return `<td class="small bad obs" title="${esc(text)}">not calibrated here</td>`;
  return `<td class="small obs" title="${esc(text)}">${o.detected ? `${o.used}/${o.detected}` : "none"}</td>`;
}

// What the road observer made of a road asset's run: its 10 s blocks (`road` of /runs, `last_run_road`).
function roadBlocks(r) {   // every complete block, read or not
  return r.read + r.settling + r.at_rest + r.slower_than_calibrated + r.without_positions + r.unsolved;
}
function roadText(r) {
  const total = roadBlocks(r);
  if (!total) return "no complete block: the run was shorter than one";
  const parts = [`${total} blocks`, `${r.read} read`];
  if (r.at_rest) parts.push(`${r.at_rest} at rest (the stroke too small)`);
  if (r.slower_than_calibrated) parts.push(`${r.slower_than_calibrated} slower than the calibration's slowest stroke`);
  if (r.without_positions) parts.push(`${r.without_positions} without positions (the potentiometer silent)`);
  if (r.unsolved) parts.push(`${r.unsolved} without a solution`);
  if (r.settling) parts.push(`${r.settling} settling after the start`);
  return parts.join(", ");
}
function roadCell(r) {
  const text = roadText(r), total = roadBlocks(r);
  if (r.why_none) return `<td class="small bad obs road" title="${esc(text)}">none read</td>`;
  return `<td class="small obs road" title="${esc(text)}">${total ? `${r.read}/${total}` : "none"}</td>`;
}

// A run sent again (a vehicle retrying, a file uploaded twice) is listed once per processing,
// but the trend counts each run once: of its copies with a summary, the completed one, else the
// newest (the daemon's `one_point_per_run`). The others say so (a helper's trial: the same run
// listed twice). The run ids with a counted copy -> that copy.
function countedCopies(runs) {
  const best = new Map();
  for (const r of runs) {
    if (!fin(r.summary_bar)) continue;
    const key = [r.status === "completed" ? 1 : 0, tsec(r.start) ?? -Infinity];
    const b = best.get(r.run_id);
    if (!b || key[0] > b.key[0] || (key[0] === b.key[0] && key[1] > b.key[1])) best.set(r.run_id, { key, r });
  }
  return new Map([...best].map(([id, b]) => [id, b.r]));
}
const REPEAT_TITLE = "the same run as another row, sent again: the trend counts the run once " +
  "(its completed copy, else the newest)";

function renderRuns(runs) {
  const tb = $("runs").tBodies[0];
  if (!runs.length) { tb.innerHTML = `<tr><td colspan="7" class="muted">no runs recorded</td></tr>`; return; }
  const counted = countedCopies(runs);
  tb.innerHTML = runs.slice(0, 20).map((r) => `<tr data-run-id="${esc(r.run_id)}">
    <td>${esc(r.run_id)}${simPill(r.simulated, "sim")}${!counted.has(r.run_id) || counted.get(r.run_id) === r ? "" : `<span class="pill repeat" title="${REPEAT_TITLE}">repeat</span>`}</td><td class="small src" title="${esc(r.source || "")}">${esc(r.source || DASH)}</td>
    <td>${fmtTime(tsec(r.start))}</td><td>${duration(tsec(r.start), tsec(r.end))}</td><td>${r.ticks ?? DASH}</td>
    <td class="${r.status === "failed" || r.status === "interrupted" ? "bad" : ""}">${esc(r.status || DASH)}</td>${r.road ? roadCell(r.road) : observerCell(r.observer)}</tr>` +
    (r.reason ? `<tr><td></td><td colspan="6" class="reason">${esc(r.reason)}</td></tr>` : "") +
    (r.road?.why_none ? `<tr><td></td><td colspan="6" class="reason">${esc(r.road.why_none)}</td></tr>` : "") +
    (r.observer?.not_calibrated_here ? `<tr><td></td><td colspan="6" class="reason">charge observer: ${esc(observerText(r.observer))}; ` +
      `the estimate kept its prior — calibrate the observer at this excitation (<code>python -m train.observer fit</code>)</td></tr>` : "")).join("");
}

function renderChanges(changes) {
  $("health-changes").innerHTML = changes.length
    ? changes.slice(0, 50).map((c) => `<li>${fmtTime(tsec(c.t))} &nbsp; ${badge(c.from)} → ${badge(c.to)}
        <span class="small">run ${esc(c.run_id)}</span></li>`).join("")
    : `<li class="muted">no health changes recorded</li>`;
}

// ---- live chart ----------------------------------------------------------------------
function chartWidth(el) { return Math.max(300, el.clientWidth); }
// A chart made while its panel was hidden took the 300 px floor and kept it (a helper's
// trial: an asset opened before it existed): its width follows the panel's.
function fitWidth(chart, el) {
  const w = chartWidth(el);
  if (Math.abs(chart.width - w) > 1) chart.setSize({ width: w, height: 260 });
}

const RUN_GAP_S = 60;   // history points further apart than this belong to different runs
function seedLive(points) {
  const L = S.live, first = L.x.length ? L.x[0] : Infinity;
  let old = points.map((p) => [tsec(p.t), p]).filter(([t]) => t < first).slice(-MAX_LIVE);
  // Only the latest run's stretch: a line drawn across the hours between runs says nothing.
  for (let i = old.length - 1; i > 0; i--) {
    if (old[i][0] - old[i - 1][0] > RUN_GAP_S) { old = old.slice(i); break; }
  }
  L.x.unshift(...old.map(([t]) => t));
  L.p.unshift(...old.map(([, p]) => p.pressure_bar));
  L.lo.unshift(...old.map(([, p]) => p.pressure_lo_bar));
  L.hi.unshift(...old.map(([, p]) => p.pressure_hi_bar));
  S.liveDirty = true;
}

function pushLive(ev) {
  // One run at a time: two runs of one asset streaming together (a file uploaded twice, a
  // replay beside the vehicle) interleaved their estimates, and the chart started afresh at
  // every step back in time (a helper's trial). The run drawn (one processing: copies of a run
  // share its id, not their `seq`) keeps the chart until it ends (its `run` event) or falls
  // silent; then the next run's estimate takes it, afresh if it was streaming alongside.
  const now = Date.now();
  if (S.liveSeq !== null && ev.seq !== S.liveSeq && now - S.liveRunAt < LIVE_SILENT_MS) {
    [S.otherSeq, S.otherRunId, S.otherRunAt] = [ev.seq, ev.run_id, now];
    return;
  }
  if (S.liveSeq !== null && ev.seq !== S.liveSeq && ev.seq === S.otherSeq) {
    S.live = { x: [], p: [], lo: [], hi: [] };   // not one line across the two runs
  }
  if (ev.seq === S.otherSeq) S.otherSeq = null;
  [S.liveSeq, S.liveRunId, S.liveRunAt] = [ev.seq, ev.run_id, now];
  const L = S.live, t = ev.t_ns / 1e9;
  if (L.x.length && t <= L.x[L.x.length - 1]) {   // a new run on an earlier clock: start afresh
    S.live = { x: [], p: [], lo: [], hi: [] };
    return pushLive(ev);
  }
  L.x.push(t);
  L.p.push(fin(ev.pressure_avg_bar) ? ev.pressure_avg_bar : ev.pressure_bar);
  L.lo.push(ev.pressure_lo_bar);
  L.hi.push(ev.pressure_hi_bar);
  // the same count off every series (a helper's trial: counted after `x` was cut, the others
  // kept their oldest values, and past 60 s the curve was drawn against the wrong times)
  const extra = L.x.length - MAX_LIVE;
  if (extra > 0) for (const k of ["x", "p", "lo", "hi"]) L[k].splice(0, extra);
  S.liveDirty = true;
}

function liveData() {
  const L = S.live, a = S.assets.get(S.selected) || {};
  const flat = (v) => L.x.map(() => (fin(v) ? v : null));
  return [L.x, L.lo, L.hi, L.p, flat(a.warn_bar), flat(a.fault_bar)];
}

function drawLive() {
  S.liveDirty = false;
  const el = $("live-chart"), data = liveData();
  const other = S.otherSeq === null || Date.now() - S.otherRunAt >= OTHER_NOTE_MS ? ""
    : S.otherRunId === S.liveRunId ? ` · run ${S.liveRunId} drawn; another copy of it is streaming too`
      : ` · run ${S.liveRunId} drawn; run ${S.otherRunId} of this asset is streaming too`;
  $("live-note").textContent = S.live.x.length
    ? `${S.live.x.length} points, ${fmtTime(S.live.x[0])} – ${fmtTime(S.live.x[S.live.x.length - 1])}${other}`
    : "no estimates yet for this asset";
  if (S.liveChart) { fitWidth(S.liveChart, el); S.liveChart.setData(data); return; }
  const line = (label, stroke, extra = {}) =>
    ({ label, stroke, width: 1, points: { show: false }, value: (u, v) => num(v), ...extra });
  S.liveChart = new uPlot({
    width: chartWidth(el), height: 260,
    scales: { x: { time: true } },
    series: [{ value: (u, v) => fmtTime(v) },
      line("lo", "rgba(43,108,176,0.35)"), line("hi", "rgba(43,108,176,0.35)"),
      line("pressure", COLORS.p, { width: 2 }),
      line("warn", COLORS.warn, { dash: [6, 4] }), line("fault", COLORS.fault, { dash: [6, 4] })],
    bands: [{ series: [2, 1], fill: COLORS.band }],   // hi down to lo
    // HH:MM, or HH:MM:SS when the ticks are less than a minute apart
    axes: [{ values: (u, xs) => xs.map((x) => fmtTime(x).slice(11, xs[1] - xs[0] < 60 ? 19 : 16)) },
      { label: "bar", size: 50 }],
  }, data, el);
}

// ---- trend chart ---------------------------------------------------------------------
// Per-run points with ±2 sd bars against calendar time, the fitted line up to the fault
// crossing (or the last run), the thresholds, and each crossing's interval shaded.
function drawTrend(t) {
  const key = JSON.stringify(t ?? null);
  if (key === S.trendKey) return;   // unchanged since the last poll
  S.trendKey = key;
  const el = $("trend-chart");
  if (S.trendChart) { S.trendChart.destroy(); S.trendChart = null; }
  $("trend-text").innerHTML = t ? trendText(t) : `<span class="muted">no trend yet</span>`;
  const pts = (t?.points || []).map((p) => ({ x: tsec(p.t), y: p.pressure_bar, sd: p.sd_bar }))
    .filter((p) => fin(p.x) && fin(p.y)).sort((p, q) => p.x - q.x);
  el.hidden = pts.length === 0;
  if (!pts.length) return;
  const cross = (c) => (c && c.t ? { t: tsec(c.t), lo: tsec(c.t_lo), hi: tsec(c.t_hi) } : null);
  const warn = cross(t.warn), fault = cross(t.fault);
  const first = pts[0].x, last = pts[pts.length - 1].x;
  // up to the fault crossing, but not so far that the runs become a dot
  const end = Math.min(Math.max(last, fault ? fault.t : last, warn ? warn.t : last),
    last + Math.max(3 * (last - first), 30 * DAY_S));
  const xmax = end + 0.15 * (end - first) + 0.5 * DAY_S;
  const x0 = first - 0.5 * DAY_S;
  // x values: the chart's edges (so that the thresholds span it), the runs, the fit's far end
  const xs = [x0, ...pts.map((p) => p.x), ...(t.fit && end > last ? [end] : []), xmax];
  if (t.fit && t.fit.onset && !xs.includes(tsec(t.fit.onset))) xs.splice(1, 0, tsec(t.fit.onset));
  xs.sort((a, b) => a - b);
  // the line, bent at the onset when the rate changed there
  const onset = t.fit && t.fit.onset ? tsec(t.fit.onset) : null;
  const fitAt = (x) => {
    if (!t.fit || x < first || x > end) return null;
    const after = t.fit.intercept_bar + t.fit.slope_bar_per_day * (x - tsec(t.fit.t0)) / DAY_S;
    return onset !== null && x < onset && fin(t.fit.slope_before_bar_per_day)
      ? after + (t.fit.slope_before_bar_per_day - t.fit.slope_bar_per_day) * (x - onset) / DAY_S : after;
  };
  const yOf = new Map(pts.map((p) => [p.x, p]));
  const asset = S.assets.get(S.selected) || {};
  const warnBar = t.warn_bar ?? asset.warn_bar ?? null, faultBar = t.fault_bar ?? asset.fault_bar ?? null;
  const data = [xs, xs.map((x) => yOf.get(x)?.y ?? null), xs.map(fitAt), xs.map(() => warnBar), xs.map(() => faultBar)];
  const ys = pts.flatMap((p) => [p.y - 2 * (p.sd || 0), p.y + 2 * (p.sd || 0)]).concat([warnBar, faultBar]);
  const ymin = Math.min(...ys.filter(fin)) - 0.5, ymax = Math.max(...ys.filter(fin)) + 0.5;

  const draw = (u) => {
    const c = u.ctx, top = u.bbox.top, h = u.bbox.height, X = (v) => u.valToPos(v, "x", true);
    const right = u.bbox.left + u.bbox.width;
    c.save();
    c.beginPath(); c.rect(u.bbox.left, top, u.bbox.width, h); c.clip();
    for (const [cr, color] of [[warn, COLORS.warn], [fault, COLORS.fault]]) {
      if (!cr) continue;
      const x0 = fin(cr.lo) ? X(cr.lo) : X(cr.t), x1 = fin(cr.hi) ? Math.min(X(cr.hi), right) : right;
      c.globalAlpha = 0.12; c.fillStyle = color; c.fillRect(x0, top, Math.max(1, x1 - x0), h);
      c.globalAlpha = 0.9; c.strokeStyle = color; c.setLineDash([4, 3]); c.lineWidth = 1.5;
      c.beginPath(); c.moveTo(X(cr.t), top); c.lineTo(X(cr.t), top + h); c.stroke();
    }
    c.setLineDash([]); c.globalAlpha = 1; c.strokeStyle = COLORS.p; c.lineWidth = 1.5;
    for (const p of pts) {   // ±2 sd bars
      const x = X(p.x), y0 = u.valToPos(p.y - 2 * p.sd, "y", true), y1 = u.valToPos(p.y + 2 * p.sd, "y", true);
      c.beginPath(); c.moveTo(x, y0); c.lineTo(x, y1); c.moveTo(x - 3, y0); c.lineTo(x + 3, y0);
      c.moveTo(x - 3, y1); c.lineTo(x + 3, y1); c.stroke();
    }
    c.restore();
  };
  S.trendChart = new uPlot({
    width: chartWidth(el), height: 260,
    scales: { x: { time: true, range: () => [x0, xmax] }, y: { range: () => [ymin, ymax] } },
    series: [{ value: (u, v) => fmtTime(v) },
      { label: "run mean", stroke: COLORS.p, paths: () => null, points: { show: true, size: 7, fill: COLORS.p },
        value: (u, v) => num(v) },
      { label: "fit", stroke: COLORS.fit, width: 1.5, points: { show: false }, value: (u, v) => num(v) },
      { label: "warn", stroke: COLORS.warn, dash: [6, 4], width: 1, points: { show: false }, value: (u, v) => num(v) },
      { label: "fault", stroke: COLORS.fault, dash: [6, 4], width: 1, points: { show: false }, value: (u, v) => num(v) }],
    // MM-DD, or MM-DD HH:MM when the ticks are less than a day apart
    axes: [{ space: 70, values: (u, xs) => xs.map((x) => fmtTime(x).slice(5, xs[1] - xs[0] < DAY_S ? 16 : 10)) },
      { label: "bar", size: 50 }],
    hooks: { draw: [draw] },
  }, data, el);
}

function trendText(t) {
  if (t.status !== "ok") return `<span class="muted">${esc(t.reason || "insufficient data")}</span>`;
  const half = fin(t.leak_rate_lo_bar_per_day) && fin(t.leak_rate_hi_bar_per_day)
    ? (t.leak_rate_hi_bar_per_day - t.leak_rate_lo_bar_per_day) / 2 : null;
  const c = (name, x) => {
    if (!x || !x.t) return `${name}: ${esc(x?.reason || "not predicted")}`;
    // to the minute when the interval is under two days (by date it read "[2023-11-20 –
    // 2023-11-20]", an interval of no width; a helper's trial)
    const span = x.t_lo && x.t_hi ? tsec(x.t_hi) - tsec(x.t_lo) : Infinity;
    const at = (v) => `<span class="nw">${span < 2 * DAY_S ? `${fmtTime(tsec(v)).slice(0, 16)} UTC` : fmtDate(tsec(v))}</span>`;
    return `${name} ≈ <b>${at(x.t)}</b> [${x.t_lo ? at(x.t_lo) : DASH} – ${x.t_hi ? at(x.t_hi) : "unbounded"}]`;
  };
  const since = t.since ? ` since the unit baseline or service of <span class="nw">${fmtDate(tsec(t.since))}</span>` : "";
  const before = t.fit && fin(t.fit.slope_before_bar_per_day) ? -t.fit.slope_before_bar_per_day : null;
  const onset = t.onset ? ` since the rate changed on <b>${fmtDate(tsec(t.onset))}</b>` +
    (before === null ? "" : ` (${num(before, 3)} bar/day before)`) : "";
  return `leak rate <b>${num(t.leak_rate_bar_per_day, 3)}</b>${half === null ? "" : ` ± ${num(half, 3)}`} bar/day${onset}; ` +
    `${c("warn", t.warn)}; ${c("fault", t.fault)} <span class="small">(${t.runs_used} runs${since})</span>`;
}

// ---- live events ---------------------------------------------------------------------
function onEstimate(ev) {
  S.liveCount += 1;
  S.lastEvent = ev;
  let a = S.assets.get(ev.asset_id);
  if (!a) {   // a new asset: its row now, the rest (and a first selection) with a poll soon
    a = { asset_id: ev.asset_id, ticks: 0, active_runs: 1, trend: null };
    S.assets.set(ev.asset_id, a);
    scheduleRefresh(1500);
  }
  // An upload of older data (a backlog) does not replace what the row shows, as on the server
  // (`/v1/assets` follows an upload only when its data are newer; a live stream always shows):
  // comparable only when both are Unix times.
  const UNIX_NS = 1e18;
  if (S.uploads.has(ev.run_id) && a.run_id && ev.run_id !== a.run_id && a.last_t_ns > UNIX_NS &&
    ev.t_ns > UNIX_NS && ev.t_ns < a.last_t_ns) return;
  for (const k of ["run_id", "pressure_bar", "pressure_avg_bar", "pressure_lo_bar", "pressure_hi_bar",
    "expected_bar", "health"]) a[k] = ev[k];
  a.last_t_ns = ev.t_ns;
  a.last_update_unix_ms = Date.now();
  a.ticks = (a.ticks || 0) + 1;
  S.fleetDirty = true;
  if (ev.asset_id === S.selected) pushLive(ev);
}

function connect() {
  // EventSource cannot set headers: the token goes as access_token (RFC 6750 §2.3).
  const es = new EventSource(TOKEN ? `v1/events?access_token=${encodeURIComponent(TOKEN)}` : "v1/events");
  const conn = (text, cls) => { $("conn").textContent = text; $("conn").className = `conn ${cls}`; };
  es.onopen = () => conn("live", "up");
  es.onerror = () => conn("reconnecting…", "down");   // EventSource retries by itself
  es.addEventListener("estimate", (e) => onEstimate(JSON.parse(e.data)));
  es.addEventListener("health", (e) => {
    const h = JSON.parse(e.data), a = S.assets.get(h.asset_id);
    if (a) { a.health = h.to; S.fleetDirty = true; }
    if (h.asset_id === S.selected) scheduleDetail();
  });
  es.addEventListener("run", (e) => {
    const r = JSON.parse(e.data);
    const upload = /^(inbox|http) /.test(r.source || "");
    if (upload && r.status === "started") S.uploads.add(r.run_id);
    else if (upload) S.uploads.delete(r.run_id);
    if (r.asset_id === S.selected) scheduleDetail();
    if (r.asset_id === S.selected && r.seq === S.liveSeq && r.status !== "started") S.liveRunAt = 0;   // ended
    if (r.status !== "started") scheduleRefresh(700);   // its trend may have moved
  });
  es.addEventListener("lagged", (e) => conn(`live (skipped ${e.data} events)`, "up"));
}

// Redraws at most 4 times a second however fast the events come.
function frame() {
  $("live-count").textContent = String(S.liveCount);
  const e = S.lastEvent;
  if (e) $("last-event").textContent = `${e.asset_id} @ ${fmtTime(e.t_ns / 1e9)}`;
  if (S.fleetDirty && Date.now() - S.fleetDrawn > 1000) renderFleet();   // rows stay clickable
  if (S.otherSeq !== null && Date.now() - S.otherRunAt >= OTHER_NOTE_MS) {   // the note goes with it
    S.otherSeq = null;
    S.liveDirty = true;
  }
  if (S.liveDirty && S.selected) drawLive();
  const a = S.assets.get(S.selected);
  if (a) headline(a);
}

function init() {
  $("fleet").tBodies[0].addEventListener("click", (e) => {
    const tr = e.target.closest("tr[data-asset-id]");
    if (tr && tr.dataset.assetId !== S.selected) select(tr.dataset.assetId);
  });
  // The keyboard: Tab reaches the rows, Enter or Space selects, the arrows move between rows
  // (a helper's trial: no asset could be selected without a mouse).
  $("fleet").tBodies[0].addEventListener("keydown", (e) => {
    const tr = e.target.closest("tr[data-asset-id]");
    if (!tr) return;
    if (e.key === "Enter" || e.key === " ") {
      e.preventDefault();
      if (tr.dataset.assetId !== S.selected) select(tr.dataset.assetId);
    } else if (e.key === "ArrowDown" || e.key === "ArrowUp") {
      e.preventDefault();
      (e.key === "ArrowDown" ? tr.nextElementSibling : tr.previousElementSibling)?.focus();
    }
  });
  window.addEventListener("resize", () => {
    for (const [chart, el] of [[S.liveChart, "live-chart"], [S.trendChart, "trend-chart"]]) {
      if (chart) chart.setSize({ width: chartWidth($(el)), height: 260 });
    }
  });
  window.addEventListener("hashchange", () => {
    const id = decodeURIComponent(location.hash.slice(1));
    if (id && id !== S.selected) select(id);
  });
  connect();
  refreshFleet();
  setInterval(frame, 250);
}

init();
