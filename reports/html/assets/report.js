/* report.html: sortable tables, plots drawn when they scroll into view, test-view viewers.
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
  document.documentElement.setAttribute("data-report-ready", "1");
})();
