// A small line chart on a canvas (training loss and PSNR against time).
export function drawChart(canvas, series, { xLabel = "", title = "" } = {}) {
  const ctx = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height, pad = 34;
  ctx.clearRect(0, 0, w, h);
  ctx.fillStyle = "#15171c";
  ctx.fillRect(0, 0, w, h);
  ctx.font = "11px sans-serif";
  ctx.fillStyle = "#ccc";
  ctx.fillText(title, pad, 14);
  ctx.fillText(xLabel, w - pad - ctx.measureText(xLabel).width, h - 4);
  const xs = series.flatMap((s) => s.points.map((p) => p[0]));
  if (!xs.length) return;
  const x0 = Math.min(...xs), x1 = Math.max(...xs) || 1;
  series.forEach((s, k) => {
    const ys = s.points.map((p) => p[1]).filter((v) => Number.isFinite(v));
    if (!ys.length) return;
    const y0 = Math.min(...ys), y1 = Math.max(...ys);
    const X = (x) => pad + ((x - x0) / (x1 - x0 || 1)) * (w - 2 * pad);
    const Y = (y) => h - pad + 8 - ((y - y0) / (y1 - y0 || 1)) * (h - 2 * pad);
    ctx.strokeStyle = s.color;
    ctx.beginPath();
    let first = true;
    for (const [x, y] of s.points) {
      if (!Number.isFinite(y)) continue;
      if (first) ctx.moveTo(X(x), Y(y)); else ctx.lineTo(X(x), Y(y));
      first = false;
    }
    ctx.stroke();
    ctx.fillStyle = s.color;
    const last = ys[ys.length - 1];
    ctx.fillText(`${s.label} ${last.toFixed(s.digits ?? 3)}`, pad + k * 130, h - 4);
  });
}

// The distribution of log10 K (the temporal variance each decomposition compares with τ): bars on a
// log count scale, static (K <= τ) blue and dynamic orange, τ the white line; the axis is
// labelled with its ends and τ, the legend says which colour is which.
export function drawHistogram(canvas, hist, tau) {
  const ctx = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height, axis = 12;
  const plot = h - axis;
  ctx.clearRect(0, 0, w, h);
  ctx.fillStyle = "#15171c";
  ctx.fillRect(0, 0, w, h);
  const edges = hist.log10_edges, counts = hist.counts;
  const max = Math.max(1, ...counts.map((c) => Math.log1p(c)));
  const lo = edges[0], hi = edges[edges.length - 1];
  const lt = Math.log10(tau);
  counts.forEach((c, i) => {
    const x = ((edges[i] - lo) / (hi - lo)) * w;
    const bw = ((edges[i + 1] - edges[i]) / (hi - lo)) * w;
    const bh = (Math.log1p(c) / max) * (plot - 10);
    ctx.fillStyle = edges[i] >= lt ? "#ff8c00" : "#5a7fd0";
    ctx.fillRect(x, plot - bh, Math.max(1, bw - 1), bh);
  });
  const xt = ((lt - lo) / (hi - lo)) * w;
  ctx.fillStyle = "#fff";
  ctx.fillRect(xt, 0, 1, plot);
  ctx.font = "9px sans-serif";
  ctx.fillStyle = "#aab";
  ctx.fillText(`${lo.toFixed(1)}`, 1, h - 2);
  const right = `${hi.toFixed(1)}`;
  ctx.fillText(right, w - ctx.measureText(right).width - 1, h - 2);
  const mid = "log₁₀ K (count: log scale)";
  ctx.fillText(mid, (w - ctx.measureText(mid).width) / 2, h - 2);
  ctx.fillStyle = "#5a7fd0";
  ctx.fillText("■ static", 2, 9);
  ctx.fillStyle = "#ff8c00";
  ctx.fillText("■ dynamic", 46, 9);
}
