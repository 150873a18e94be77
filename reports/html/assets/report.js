/* report.html: sortable tables, plots drawn when they scroll into view, test-view viewers, video players.
   Every string from the report's data goes into the page as text (textContent / attributes), never as markup. */
(function () {
  "use strict";
  var DATA = JSON.parse(document.getElementById("report-data").textContent);

  function el(tag, attrs, text) {
    var e = document.createElement(tag);
    Object.keys(attrs || {}).forEach(function (k) { e.setAttribute(k, attrs[k]); });
    if (text !== undefined && text !== null) e.textContent = String(text);
    return e;
  }

  /* ---- sortable tables: a click on a header sorts by that column, a second click reverses ---- */
  function cellKey(row, col) {
    var c = row.cells[col];
    if (!c) return { num: null, text: "" };
    var s = c.getAttribute("data-sort");
    return { num: s === null ? null : parseFloat(s), text: c.textContent.trim() };
  }
  function sortTable(table, col, th) {
    var dir = th.getAttribute("aria-sort") === "ascending" ? -1 : 1;
    Array.prototype.forEach.call(table.tHead.rows[0].cells, function (h) { h.removeAttribute("aria-sort"); });
    th.setAttribute("aria-sort", dir === 1 ? "ascending" : "descending");
    var body = table.tBodies[0];
    var rows = Array.prototype.slice.call(body.rows);
    var numeric = th.classList.contains("num");
    rows.sort(function (a, b) {
      var x = cellKey(a, col), y = cellKey(b, col);
      if (numeric) {  // rows without a number ("—") stay last in both directions
        if (x.num === null || isNaN(x.num)) return (y.num === null || isNaN(y.num)) ? 0 : 1;
        if (y.num === null || isNaN(y.num)) return -1;
        return dir * (x.num - y.num);
      }
      return dir * x.text.localeCompare(y.text, undefined, { numeric: true });
    });
    rows.forEach(function (r) { body.appendChild(r); });
  }
  Array.prototype.forEach.call(document.querySelectorAll("table.sortable"), function (table) {
    Array.prototype.forEach.call(table.tHead.rows[0].cells, function (th, col) {
      th.tabIndex = 0;
      th.addEventListener("click", function () { sortTable(table, col, th); });
      th.addEventListener("keydown", function (ev) { if (ev.key === "Enter") sortTable(table, col, th); });
    });
  });

  /* ---- run filter: hides rows of the runs table that do not contain the text ---- */
  var filter = document.getElementById("runs-filter");
  if (filter) {
    filter.addEventListener("input", function () {
      var q = filter.value.toLowerCase();
      Array.prototype.forEach.call(document.querySelectorAll("#runs-table tbody tr"), function (tr) {
        tr.hidden = q !== "" && tr.textContent.toLowerCase().indexOf(q) < 0;
      });
    });
  }

  /* ---- plots: drawn once each when near the viewport (a report of hundreds of runs stays fast) ---- */
  function draw(fig) {
    var div = document.getElementById(fig.id);
    if (!div || div.getAttribute("data-state")) return;
    if (typeof window.Plotly === "undefined") {
      div.setAttribute("data-state", "no-plotly");
      div.textContent = "Plot not drawn: the plotting library is not in this page (" + DATA.plotly_missing + ").";
      return;
    }
    div.setAttribute("data-state", "drawing");
    window.Plotly.newPlot(div, fig.data, fig.layout, { responsive: true, displaylogo: false })
      .then(function () { div.setAttribute("data-state", "drawn"); },
            function (err) { div.setAttribute("data-state", "failed"); console.error("plot " + fig.id + ": " + err); });
  }
  var figures = DATA.figures || [];
  if ("IntersectionObserver" in window) {
    var byId = {};
    figures.forEach(function (f) { byId[f.id] = f; });
    var io = new IntersectionObserver(function (entries) {
      entries.forEach(function (e) {
        if (e.isIntersecting) { io.unobserve(e.target); draw(byId[e.target.id]); }
      });
    }, { rootMargin: "400px 0px" });
    figures.forEach(function (f) { var d = document.getElementById(f.id); if (d) io.observe(d); });
  } else {
    figures.forEach(draw);
  }

  /* ---- test-view viewers: ground truth | each method | |error|, side by side or flipped in place ---- */
  function image(src, alt, caption) {
    var fig = el("figure", { "class": "tile" });
    if (caption) fig.appendChild(el("figcaption", {}, caption));
    if (src) {
      var img = el("img", { src: src, alt: alt, loading: "lazy", decoding: "async", title: alt });
      img.addEventListener("error", function () {
        fig.classList.add("broken");
        fig.appendChild(el("span", { "class": "missing" }, "image not found: " + src));
      });
      fig.appendChild(img);
    } else {
      fig.appendChild(el("span", { "class": "missing" }, "not saved"));
    }
    return fig;
  }
  function fmt(x) { return (typeof x === "number") ? x.toFixed(2) + " dB" : ""; }

  function buildViewer(v) {
    var root = document.getElementById(v.id);
    if (!root) return;
    var controls = el("div", { "class": "controls" });
    var groupSel = el("select", { "aria-label": "configuration" });
    v.groups.forEach(function (g, i) { groupSel.appendChild(el("option", { value: String(i) }, g.label)); });
    var viewSel = el("select", { "aria-label": "test view" });
    v.views.forEach(function (name, i) { viewSel.appendChild(el("option", { value: String(i) }, name)); });
    var modeSel = el("select", { "aria-label": "layout" });
    modeSel.appendChild(el("option", { value: "grid" }, "side by side"));
    modeSel.appendChild(el("option", { value: "flip" }, "flip between methods"));
    [["configuration ", groupSel], ["view ", viewSel], ["layout ", modeSel]].forEach(function (p) {
      var l = el("label", {}, p[0]); l.appendChild(p[1]); controls.appendChild(l);
    });
    var stage = el("div", { "class": "stage" });
    root.appendChild(controls);
    root.appendChild(stage);

    function render() {
      var g = v.groups[+groupSel.value], view = v.views[+viewSel.value];
      stage.textContent = "";
      var gt = v.gt[view];
      if (modeSel.value === "grid") {
        var grid = el("div", { "class": "tiles" });
        var col = el("div", { "class": "col" });
        col.appendChild(el("div", { "class": "cap" }, view));
        col.appendChild(image(gt, "ground truth " + view, "ground truth"));
        grid.appendChild(col);
        g.runs.forEach(function (r) {
          var c = el("div", { "class": "col" });
          c.appendChild(el("div", { "class": "cap", title: r.run }, r.method + " " + fmt(r.psnr[view])));
          c.appendChild(image(r.render[view], r.method + " render " + view + " (" + r.run + ")", "render"));
          if (gt || r.error[view]) {
            c.appendChild(image(r.error[view], r.method + " |error| " + view + " (" + r.run + ")", "|error|"));
          }
          grid.appendChild(c);
        });
        stage.appendChild(grid);
        return;
      }
      var slots = [{ label: "ground truth", src: gt }];
      g.runs.forEach(function (r) {
        slots.push({ label: r.method + " " + fmt(r.psnr[view]), src: r.render[view], run: r.run });
        if (r.error[view]) slots.push({ label: r.method + " |error|", src: r.error[view], run: r.run });
      });
      var slider = el("input", { type: "range", min: "0", max: String(slots.length - 1), value: "1",
                                 "aria-label": "image" });
      var cap = el("div", { "class": "cap" });
      var holder = el("div", { "class": "flip" });
      function show() {
        var s = slots[+slider.value];
        cap.textContent = s.label + (s.run ? " — " + s.run : "");
        holder.textContent = "";
        holder.appendChild(image(s.src, s.label + " " + view));
      }
      slider.addEventListener("input", show);
      stage.appendChild(slider);
      stage.appendChild(cap);
      stage.appendChild(holder);
      show();
    }
    [groupSel, viewSel, modeSel].forEach(function (s) { s.addEventListener("change", render); });
    render();
  }
  (DATA.viewers || []).forEach(buildViewer);

  /* ---- video players: each method's flythrough in step, one control for all, the popping strip ---- */
  var ROW = 9, TOP = 12;  // the strip: px per method row, px above the rows for the worst-pair mark

  function heat(t) {  // t in [0, 1] -> the error maps' ramp: black -> red -> yellow -> white
    var x = Math.max(0, Math.min(1, t)) * 3;
    return "rgb(" + [x, x - 1, x - 2].map(function (c) { return Math.round(255 * Math.max(0, Math.min(1, c))); }).join(",") + ")";
  }

  function buildPlayer(p) {
    var root = document.getElementById(p.id);
    if (!root) return;
    var n = p.frames, fps = p.fps;
    var state = { frame: 0, playing: false, visible: false, group: 0, videos: [], timer: null };
    var controls = el("div", { "class": "controls" });
    var groupSel = el("select", { "aria-label": "configuration" });
    p.groups.forEach(function (g, i) { groupSel.appendChild(el("option", { value: String(i) }, g.label)); });
    var playBtn = el("button", { type: "button", "class": "play" }, "▶ play");
    var speedSel = el("select", { "aria-label": "speed" });
    [1, 0.5, 0.25].forEach(function (r) { speedSel.appendChild(el("option", { value: String(r) }, r + "×")); });
    var errBox = el("input", { type: "checkbox", "class": "error-toggle" });
    var errLabel = el("label", {}, " warped error");
    errLabel.insertBefore(errBox, errLabel.firstChild);
    var frameLabel = el("span", { "class": "frame" });
    var confLabel = el("label", {}, "configuration ");
    confLabel.appendChild(groupSel);
    [confLabel, playBtn, speedSel, errLabel, frameLabel].forEach(function (c) { controls.appendChild(c); });
    var stage = el("div", { "class": "tiles" });
    var scrub = el("input", { type: "range", min: "0", max: String(n - 1), value: "0", step: "1", "class": "scrub",
                              "aria-label": "frame" });
    var strip = el("canvas", { "class": "popstrip", "aria-label": "warped MSE per frame; click to go to a frame" });
    [controls, stage, scrub, strip].forEach(function (c) { root.appendChild(c); });

    function group() { return p.groups[state.group]; }
    function master() { return state.videos[0]; }
    function active() { return state.videos.length > 0 && state.videos[0].hasAttribute("src"); }
    function time(k) { return (k + 0.5) / fps; }

    function tiles() {
      stage.textContent = "";
      state.videos = [];
      group().videos.forEach(function (v) {
        var tile = el("figure", { "class": "vtile", title: v.run });
        tile.appendChild(el("div", { "class": "cap" }, v.method + (typeof v.psnr === "number" ? " " + fmt(v.psnr) : "")));
        var box = el("div", { "class": "vbox" });
        [["frames", v.src, v.poster], ["errors", v.error_src, v.error_poster]].forEach(function (x) {
          var vid = el("video", { "class": x[0], poster: x[2], "data-src": x[1], muted: "", playsinline: "",
                                  preload: "auto", "aria-label": v.method + " " + x[0] + " (" + v.run + ")" });
          vid.muted = true;
          vid.addEventListener("error", function () { tile.classList.add("broken"); });
          box.appendChild(vid);
          state.videos.push(vid);
        });
        tile.appendChild(box);
        tile.appendChild(el("figcaption", {}, v.budget + " · seed " + v.seed));
        stage.appendChild(tile);
      });
      master().addEventListener("ended", function () { if (state.playing) { seek(0); playAll(); } });
      drawStrip();
    }
    function activate() {
      if (active()) return;
      state.videos.forEach(function (v) {
        v.src = v.getAttribute("data-src");
        v.playbackRate = +speedSel.value;
        v.currentTime = time(state.frame);
      });
    }
    function deactivate() {  // out of view: its decoders and buffers are released
      stop();
      state.videos.forEach(function (v) { v.pause(); v.removeAttribute("src"); v.load(); });
    }
    function seek(k) {
      state.frame = Math.max(0, Math.min(n - 1, k));
      if (active()) state.videos.forEach(function (v) { v.currentTime = time(state.frame); });
      show();
    }
    function playAll() {
      state.videos.forEach(function (v) {
        var r = v.play();
        if (r && r.catch) r.catch(function () { /* paused before it started */ });
      });
    }
    function play() {
      activate();
      state.playing = true;
      playBtn.textContent = "❚❚ pause";
      playAll();
      state.timer = setInterval(follow, 40);
    }
    function stop() {
      if (state.timer) clearInterval(state.timer);
      state.timer = null;
      state.playing = false;
      playBtn.textContent = "▶ play";
      state.videos.forEach(function (v) { v.pause(); });
    }
    function pause() {
      stop();
      if (active()) seek(Math.min(n - 1, Math.floor(master().currentTime * fps)));
    }
    function follow() {  // the first video is the clock; the others are brought back when they drift
      var t = master().currentTime;
      state.videos.forEach(function (v) { if (v !== master() && Math.abs(v.currentTime - t) > 1.5 / fps) v.currentTime = t; });
      state.frame = Math.min(n - 1, Math.floor(t * fps));
      show();
    }
    function show() {
      scrub.value = String(state.frame);
      frameLabel.textContent = "frame " + state.frame + " / " + (n - 1);
      drawStrip();
    }

    function drawStrip() {
      var vids = group().videos, w = Math.max(100, Math.round(strip.clientWidth || scrub.clientWidth || 600));
      strip.width = w;
      strip.height = TOP + ROW * vids.length + 2;
      var ctx = strip.getContext("2d");
      ctx.fillStyle = "#f4f4f4";
      ctx.fillRect(0, 0, w, strip.height);
      var vmax = 0, worst = null;
      vids.forEach(function (v, r) {
        v.mse.forEach(function (m, j) { if (m !== null && m > vmax) { vmax = m; worst = [r, j]; } });
      });
      var cell = w / n;
      vids.forEach(function (v, r) {
        v.mse.forEach(function (m, j) {
          if (m === null) return;
          ctx.fillStyle = heat(vmax > 0 ? m / vmax : 0);
          ctx.fillRect(Math.floor(j * cell), TOP + r * ROW, Math.ceil(cell), ROW - 1);
        });
        if (v.worst !== null) {  // each method's worst pair
          ctx.fillStyle = "#06c";
          ctx.fillRect(Math.floor((v.worst + 0.5) * cell) - 1, TOP + r * ROW + ROW - 3, 3, 2);
        }
      });
      if (worst) {  // the worst pair of all
        var x = (worst[1] + 0.5) * cell;
        ctx.fillStyle = "#c00";
        ctx.beginPath(); ctx.moveTo(x - 5, 1); ctx.lineTo(x + 5, 1); ctx.lineTo(x, TOP - 2); ctx.fill();
        strip.setAttribute("data-worst", String(worst[1]));
      }
      ctx.fillStyle = "#036";
      ctx.fillRect(Math.floor((state.frame + 0.5) * cell) - 1, 0, 2, strip.height);
    }
    function frameAt(ev) {
      var r = strip.getBoundingClientRect();
      return Math.max(0, Math.min(n - 1, Math.floor((ev.clientX - r.left) / r.width * n)));
    }
    strip.addEventListener("click", function (ev) { if (state.playing) stop(); seek(frameAt(ev)); });
    strip.addEventListener("mousemove", function (ev) {
      var j = frameAt(ev);
      strip.title = "frame " + j + ": " + group().videos.map(function (v) {
        return v.method + " " + (v.mse[j] === null ? "—" : v.mse[j].toPrecision(3));
      }).join(", ");
    });
    scrub.addEventListener("input", function () { if (state.playing) stop(); seek(+scrub.value); });
    playBtn.addEventListener("click", function () { if (state.playing) pause(); else play(); });
    speedSel.addEventListener("change", function () {
      state.videos.forEach(function (v) { v.playbackRate = +speedSel.value; });
    });
    errBox.addEventListener("change", function () { root.classList.toggle("show-error", errBox.checked); });
    groupSel.addEventListener("change", function () {
      deactivate();
      state.group = +groupSel.value;
      tiles();
      if (state.visible) activate();
      seek(state.frame);
    });
    tiles();
    show();
    if ("IntersectionObserver" in window) {
      new IntersectionObserver(function (entries) {
        entries.forEach(function (e) {
          state.visible = e.isIntersecting;
          if (e.isIntersecting) activate(); else deactivate();
        });
      }, { rootMargin: "300px 0px" }).observe(root);
    } else {
      state.visible = true;
      activate();
    }
  }
  (DATA.players || []).forEach(buildPlayer);
  document.documentElement.setAttribute("data-report-ready", "1");
})();
