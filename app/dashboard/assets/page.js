(function () {
  // What the gate adds to the page (docs/page-access.md, "What the page adds"). window.OMNI_PAGE.kind
  // says which page this is: "live", "fleet", or "replay" (a replay commands nothing: its bar has no
  // STOP and says so, and no key stops anything there).
  var KIND = (window.OMNI_PAGE || {}).kind || "live";
  var LOST_MS = 1000 * ((window.OMNI_PAGE || {}).lost_s || 1);  // no tick for this long: not connected
  var WATCHDOG_S = (window.OMNI_PAGE || {}).watchdog_s;  // the robots' own watchdog (the link's)
  var NAMES = ["STOP", "STOP every leader"];
  var STATE = /^(running|STOPPED|PAUSED|recorded|leaders)/;
  function panelStop() {
    return Array.prototype.find.call(document.querySelectorAll("button"), function (b) {
      return NAMES.indexOf(b.textContent.trim()) >= 0 && !b.closest("#omni-stopbar");
    });
  }
  function panelButton(name) {
    return Array.prototype.find.call(document.querySelectorAll("button"), function (b) {
      return b.textContent.trim() === name && !b.closest("#omni-stopbar");
    });
  }
  function panelCheckbox(name) {
    var label = Array.prototype.find.call(document.querySelectorAll("label"), function (l) {
      return l.textContent.trim() === name;
    });
    var id = label && label.getAttribute("for");
    return id ? document.getElementById(id) : null;
  }
  function lineOf(re) {
    var strong = Array.prototype.find.call(document.querySelectorAll("strong"), function (e) {
      return re.test(e.textContent.trim()) && !e.closest("#omni-stopbar");
    });
    if (!strong || !strong.parentNode) return "";
    var text = "";
    for (var n = strong; n && n.nodeName !== "BR"; n = n.nextSibling) text += n.textContent;
    return text.trim();
  }
  function panelState() {
    var strong = Array.prototype.find.call(document.querySelectorAll("strong"), function (e) {
      return STATE.test(e.textContent.trim()) && !e.closest("#omni-stopbar");
    });
    return strong ? strong.parentNode : null;
  }
  function press() {
    if (KIND === "replay" || link.down) return false;  // not connected: a click would reach nothing
    var stop = panelStop();
    if (stop && !stop.disabled) { stop.click(); return true; }
    return false;
  }
  // Something a key would close is open: a dropdown's list, a menu, a dialog (modal), a popover.
  function somethingOpen() {
    var open = document.querySelectorAll("[role=listbox], [role=menu], [role=dialog], .mantine-Popover-dropdown,"
                                         + " .mantine-Combobox-dropdown, [aria-expanded=true][aria-haspopup]");
    return Array.prototype.some.call(open, function (e) {
      var r = e.getBoundingClientRect();
      return r.width > 0 && r.height > 0 && getComputedStyle(e).visibility !== "hidden";
    });
  }
  // Keys: Space outside a text field presses STOP; Escape presses STOP only when nothing is open (with
  // a dropdown or a dialog open, Escape closes it and stops nothing).
  document.addEventListener("keydown", function (e) {
    if (e.ctrlKey || e.altKey || e.metaKey) return;
    var typing = /^(INPUT|TEXTAREA|SELECT)$/.test((document.activeElement || {}).tagName || "");
    var stops = (e.key === " " && !typing) || (e.key === "Escape" && !somethingOpen());
    if (stops && press()) e.preventDefault();
  }, true);
  function bar() {
    var el = document.getElementById("omni-stopbar");
    if (el || !document.body) return el;
    el = document.createElement("div");
    el.id = "omni-stopbar";
    el.setAttribute("role", "region");
    el.setAttribute("aria-label", KIND === "replay" ? "replay" : "emergency stop");
    if (KIND === "replay") el.className = "omni-replay";
    var b = document.createElement("button");
    b.type = "button";
    b.textContent = "STOP (Space)";
    b.title = "Stop the leader and every follower now (Space, or Escape when no menu is open)";
    b.addEventListener("click", press);
    if (KIND === "replay") b.style.display = "none";  // a replay commands no robot: no STOP to press
    var t = document.createElement("span");
    t.id = "omni-stopstate";
    var age = document.createElement("span");
    age.id = "omni-linkage";  // not connected: the last t and loop rate, greyed, with their age
    var alarm = document.createElement("div");
    alarm.id = "omni-alarm";
    alarm.setAttribute("role", "alert");
    var text = document.createElement("span");
    var ack = document.createElement("button");
    ack.type = "button";
    ack.textContent = "Acknowledge";
    ack.addEventListener("click", function () { var a = panelButton("Acknowledge alarms"); if (a && !a.disabled) a.click(); });
    alarm.appendChild(text);
    alarm.appendChild(ack);
    el.appendChild(b);
    el.appendChild(t);
    el.appendChild(age);
    document.body.appendChild(el);
    document.body.appendChild(alarm);  // its own box under the bar: the bar holds one button, STOP
    return el;
  }
  // The bar sits over the 3D view, left of the panel: never over the panel's header or the camera.
  function place(el) {
    var root = panelRoot() || paperOf(panelStop());
    var left = root ? root.getBoundingClientRect().left : window.innerWidth;
    var room = Math.max(220, left - 16);
    el.style.maxWidth = room + "px";
    el.style.left = left > 236 ? "8px" : "";
    el.style.transform = left > 236 ? "none" : "";
  }
  // a link to another page (a replay on its own port) opens in a new tab, never in place of this
  // one; "Replay in a new tab" opens the tab at the click (browsers allow a tab only then) and
  // sends it to the replay's link once the server has made it
  function others() {
    return Array.prototype.map.call(document.querySelectorAll("a[href]"), function (a) { return a.href; })
      .filter(function (h) { return h.indexOf(location.origin + "/") !== 0 && /^https?:/.test(h); });
  }
  document.addEventListener("click", function (e) {
    var target = e.target && e.target.closest ? e.target : null;
    var a = target && target.closest("a[href]");
    if (a && /^https?:/.test(a.href) && a.origin !== location.origin) {
      e.preventDefault();
      window.open(a.href, "_blank", "noopener");
      return;
    }
    var b = target && target.closest("button");
    if (!b || b.disabled || b.textContent.trim() !== "Replay in a new tab") return;
    var before = {};
    others().forEach(function (h) { before[h] = true; });
    var tab = window.open("about:blank", "_blank");
    var tries = 0;
    var wait = setInterval(function () {
      var fresh = others().filter(function (h) { return !before[h]; });
      if (fresh.length && tab) { tab.location.href = fresh[0]; clearInterval(wait); }
      else if (++tries > 120) { clearInterval(wait); if (tab) tab.close(); }  // 30 s: nothing came (the page says why)
    }, 250);
  }, true);
  // "Wide panel": the control panel (its charts and the camera) at half the window, and back;
  // this browser only (the page's width is a matter for whoever looks at it)
  function paperOf(n) {
    var root = null;
    for (; n; n = n.parentElement) if (n.classList && n.classList.contains("mantine-Paper-root")) root = n;
    return root;
  }
  function panelRoot() {
    var n = document.querySelector(".uplot") || document.querySelector("img[src^='blob:']"), root = null;
    for (; n; n = n.parentElement) if (n.classList && n.classList.contains("mantine-Paper-root")) root = n;
    return root;
  }
  function widen(on) {
    var root = panelRoot();
    if (!root) return false;
    root.style.width = on ? "50vw" : "";
    root.style.maxWidth = on ? "50vw" : "";
    root.style.transform = "";
    var r = root.getBoundingClientRect();
    if (on && r.right > window.innerWidth) root.style.transform = "translateX(" + (window.innerWidth - r.right - 8) + "px)";
    Array.prototype.forEach.call(root.querySelectorAll("img[src^='blob:']"), function (img) {
      img.style.width = on ? "100%" : "";
    });
    window.dispatchEvent(new Event("resize"));
    return true;
  }
  function wideButton() {
    var b = document.getElementById("omni-wide");
    if (b || !document.body || !panelRoot()) return b;
    b = document.createElement("button");
    b.id = "omni-wide";
    b.type = "button";
    b.textContent = "Wide panel";
    b.title = "the panel, its charts and the camera at half the window (this browser only)";
    b.addEventListener("click", function () {
      var on = b.getAttribute("aria-pressed") !== "true";
      if (widen(on)) { b.setAttribute("aria-pressed", on ? "true" : "false"); b.textContent = on ? "Narrow panel" : "Wide panel"; }
    });
    document.body.appendChild(b);
    return b;
  }
  // Light mode: when this browser's main thread is busy more than half of each second for 3 s
  // (long tasks: software rendering, no GPU), it ticks the panel's "Light mode": the server then sends
  // the 3D view once a second without shadows and the charts every 2 s, so the page's main thread is
  // free for clicks and STOP. window.omniFps and window.omniBusy: the browser tests print them.
  var LIGHT_BUSY = 0.5, busyMs = 0, slowSeconds = 0, frames = -1;
  window.omniFps = NaN;  // frames drawn in the last sample (one second in five: a perpetual count would
  window.omniBusy = NaN;  // itself make the browser draw all the time); the main thread's busy share
  if (window.PerformanceObserver) {
    try {
      new PerformanceObserver(function (list) {
        list.getEntries().forEach(function (e) { busyMs += e.duration; });
      }).observe({type: "longtask", buffered: false});
    } catch (err) { /* no long-task timing here: light mode stays the operator's choice */ }
  }
  function count() { if (frames >= 0) { frames++; requestAnimationFrame(count); } }
  setInterval(function () {
    frames = 0;
    requestAnimationFrame(count);
    setTimeout(function () { window.omniFps = frames; frames = -1; }, 1000);
  }, 5000);
  setInterval(function () {
    window.omniBusy = Math.min(1, busyMs / 1000);
    busyMs = 0;
    slowSeconds = window.omniBusy > LIGHT_BUSY ? slowSeconds + 1 : 0;
    if (slowSeconds >= 3 && !document.body.classList.contains("omni-light")) {
      light(true);
      var box = panelCheckbox("Light mode");  // and the server sends less (an operator's page; a viewer's is refused)
      if (box && !box.checked && !box.disabled) box.click();
    }
  }, 1000);
  function light(on) {
    document.body.classList.toggle("omni-light", on);
  }
  window.omniLight = light;
  // The robot card (a robot clicked in 3D, or its name): brought into view when another robot is
  // chosen, wherever the panel was scrolled; left alone while the same robot's figures change.
  var CARD = /^F\d+ \((tracked|not tracked)\)/, shownCard = "";
  function card() {
    var strong = Array.prototype.find.call(document.querySelectorAll("strong"), function (e) {
      return /^F\d+$/.test(e.textContent.trim()) && e.parentNode && CARD.test(e.parentNode.textContent.trim());
    });
    return strong ? strong.parentNode : null;
  }
  function showCard() {
    var c = card(), who = c ? c.textContent.trim().split(" ")[0] : "";
    if (who === shownCard) return;
    shownCard = who;
    if (c) c.scrollIntoView({block: "nearest"});
  }
  // The link to the loop (live page): the loop's state line carries the tick it was drawn from
  // (data-omni-beat), redrawn about five times a second. No new tick for LOST_MS, whatever the cause
  // (the service gone, the loop's process dead, the network down), or the page saying the loop has
  // ended: NOT CONNECTED, the bar full width, its STOP and the panel's disabled, the last t and loop
  // rate greyed with their age. viser reconnects by itself; the first new tick says so.
  var link = {down: false, tick: null, t: "", hz: "", state: "", at: performance.now(), since: 0,
              back: 0, gap: 0, checked: performance.now(), stopSeen: false};
  window.omniLink = link;  // the browser tests read it
  function beatOf() {
    var el = Array.prototype.find.call(document.querySelectorAll("[data-omni-beat]"), function (e) {
      return !e.closest("#omni-stopbar");
    });
    return el ? {tick: el.getAttribute("data-omni-beat"), t: el.getAttribute("data-t"), hz: el.getAttribute("data-hz")}
              : null;
  }
  function clock(ms) {
    var d = new Date(Date.now() - (performance.now() - ms));
    return d.toTimeString().slice(0, 8);
  }
  function watchLink() {
    if (KIND !== "live") return;
    var now = performance.now();
    var late = now - link.checked > 400;  // this page's own thread was held (a busy browser): judged next time
    link.checked = now;
    var b = beatOf();
    if (b && b.tick !== link.tick) {
      var first = link.tick === null;  // the page's first tick: connected, not reconnected
      link.tick = b.tick; link.t = b.t; link.hz = b.hz; link.at = now;
      link.state = (lineOf(STATE).match(/^(running|STOPPED|PAUSED)/) || [""])[0];
      if (link.down) {
        link.down = false;
        if (!first) { link.back = now; link.gap = (now - link.since) / 1000; link.reconnects = (link.reconnects || 0) + 1; }
      }
    }
    if (!link.stopSeen) link.stopSeen = !!panelStop();
    if (!link.stopSeen) return;  // a page with no STOP (the calibration page) has no loop to lose
    var ended = !!lineOf(/^THE LOOP HAS ENDED/);
    if (!link.down && (ended || (!late && now - link.at > LOST_MS))) {
      link.down = true;
      link.downAt = now;  // (the browser tests print how long after the last tick it was said)
      link.since = link.tick === null ? now : link.at;
      link.back = 0;
    }
  }
  function linkText() {
    var wd = WATCHDOG_S ? " in " + WATCHDOG_S + " s" : "";
    return "NOT CONNECTED — STOP unavailable from this page; robots stop on their own watchdog" + wd
      + " once no command reaches them (a loop that still runs keeps driving them: stop it at the leader)";
  }
  function ageText() {
    if (link.tick === null) return "no tick from the loop yet · reconnecting by itself";
    var age = (performance.now() - link.at) / 1000;
    return "last from the loop " + age.toFixed(1) + " s ago (" + clock(link.at) + "): " + (link.state || "state")
      + " · t = " + link.t + " s · loop " + link.hz + " Hz · reconnecting by itself";
  }
  // The bar and the card follow the panel as soon as it changes (a STOP shown on the panel is on the
  // bar in the same moment), and four times a second for the layout.
  function refresh() {
    var wide = wideButton();
    if (wide && wide.getAttribute("aria-pressed") === "true") {  // a panel redrawn since keeps it
      var root = panelRoot();
      if (root && root.style.width !== "50vw") widen(true);
    }
    var el = bar(), stop = panelStop();
    if (!el) return;
    watchLink();
    var down = KIND === "live" && link.down;
    var show = KIND === "replay" || !!stop || down;
    el.style.display = show ? "flex" : "none";
    el.classList.toggle("omni-down", down);
    var said = panelState();  // the panel's own state line: greyed too (it is no longer the loop's)
    [stop, said].forEach(function (n) {
      if (n && down) n.setAttribute("data-omni-down", "");
      else if (n) n.removeAttribute("data-omni-down");
    });
    if (!show) return;
    if (!down) place(el);
    var state = lineOf(STATE);
    if (KIND === "replay") {
      el.firstChild.disabled = true;
      setText(el.children[1], "REPLAY — no robot is controlled" + (state ? " · " + state : ""));
    } else if (down) {
      el.firstChild.disabled = true;
      setText(el.firstChild, "STOP unavailable");
      setText(el.children[1], linkText());
      setText(el.children[2], ageText());
    } else {
      el.firstChild.disabled = stop.disabled;
      setText(el.firstChild, "STOP (Space)");
      var back = link.back && performance.now() - link.back < BACK_MS
        ? " · RECONNECTED at " + clock(link.back) + " after " + link.gap.toFixed(1) + " s without the loop" : "";
      setText(el.children[1], state + (document.body.classList.contains("omni-light") ? " · light mode" : "") + back);
      setText(el.children[2], "");
    }
    var alarm = KIND === "replay" ? "" : lineOf(/^ALARM/);
    var box = document.getElementById("omni-alarm");
    var r = el.getBoundingClientRect();
    box.style.top = (r.bottom + 4) + "px";
    box.style.left = r.left + "px";
    box.style.maxWidth = el.style.maxWidth;
    box.style.display = alarm ? "flex" : "none";
    el.classList.toggle("omni-alarmed", !!alarm);
    if (alarm) {
      setText(box.firstChild, alarm + pageCause());
      var ack = panelButton("Acknowledge alarms");
      box.lastChild.style.display = ack && !ack.disabled ? "" : "none";
    }
    if (KIND === "live") showCard();
  }
  // A cause on this side, named beside the alarm: this browser busy (long tasks over half of each
  // second) while it runs on the loop's own machine (a page opened on the loopback address) takes
  // the CPU the loop needs; elsewhere, it only makes what this page shows late.
  function pageCause() {
    var busy = window.omniBusy;
    if (!(busy > LIGHT_BUSY)) return "";
    var share = Math.round(100 * busy) + " % of its main thread";
    return /^(127\.|localhost$|\[::1\]$)/.test(location.hostname)
      ? " · this browser, on the loop's machine, is busy (" + share + "): it takes the loop's CPU"
      : " · this browser is busy (" + share + "): what it shows is late";
  }
  function setText(node, text) { if (node.textContent !== text) node.textContent = text; }  // no change: no mutation
  setInterval(refresh, 250);
  var BACK_MS = 8000;  // how long the bar says the link came back
  if (KIND === "live") setInterval(function () {  // the link is judged ten times a second
    var was = link.down;
    watchLink();
    if (link.down !== was) refresh();
    else if (link.down) { var el = document.getElementById("omni-stopbar"); if (el) setText(el.children[2], ageText()); }
  }, 100);
  var pending = false;
  function watch() {
    if (!document.body) { setTimeout(watch, 50); return; }
    new MutationObserver(function (records) {
      var ours = records.every(function (r) {
        var n = r.target.nodeType === 1 ? r.target : r.target.parentNode;
        return n && n.closest && n.closest("#omni-stopbar, #omni-alarm");
      });
      if (ours || pending) return;
      pending = true;
      setTimeout(function () { pending = false; refresh(); }, 0);
    }).observe(document.body, {subtree: true, childList: true, characterData: true});
  }
  watch();
})();
