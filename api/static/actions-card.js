// The loop page's actions card: the TUNE form, TBRK, and "Apply gains…" with its confirmation of every parameter
// that changes. Each button is enabled only when the loop's state allows it and the token may operate.

import { ApiError, get, post } from "./api.js";
import { paramLabel } from "./display.js";
import { $, esc, fill, h } from "./dom.js";
import { changes, paramText } from "./gains.js";
import { notify } from "./notices.js";
import { unitsOf } from "./units.js";
import { canOperate, me } from "./who.js";

// `page` is the loop page's record (page.loop: the loop's status); `onApplied(status)` gets the loop's status after
// an apply (the result card then shows the session as applied); `redraw()` redraws the loop page's cards from
// page.loop (a command sent or answered changes what may be pressed, on this card and health's "Tune now").
export function actionsCard(page, onApplied, redraw) {
  const id = page.id;
  const node = h("section", { class: "card actions", id: "actions" });
  // The commands sent and not settled yet: their buttons stay disabled whatever redraws the card meanwhile (a loop
  // state or health event arriving during the request re-enabled TUNE, offering a second one).
  const pending = commands(redraw);
  // The form, built once (so typing is not lost on updates); its defaults from the loop when the API gives them.
  const form = tuneForm(id, pending);
  const actionMsg = h("div", { class: "form-msg", id: "action-msg" });
  const tbrk = h("button", { type: "button", class: "danger", id: "tbrk", onclick: () => {
    if (pending.has("tbrk")) return;
    fill(actionMsg);
    // Settled once the state shows the experiment ended (the daemon restores the loop first).
    pending.run("tbrk", () => post(`/loops/${esc(id)}/break`),
      (answer) => (loop) => !loop.tbsy || loop.session !== answer.session, (err) => notify(err, actionMsg));
  } }, "TBRK — abort");
  const apply = h("button", { type: "button", class: "secondary", id: "apply", onclick: () => confirmApply() }, "Apply gains…");
  const applyBox = h("div", { class: "apply-box", id: "apply-box" });
  const roleNote = h("p", { class: "muted small", id: "role-note" });
  fill(node, h("h2", {}, "Actions"), form.node, h("div", { class: "buttons" }, tbrk, apply), applyBox, actionMsg, roleNote);
  form.onError = (err) => notify(err, actionMsg);
  form.onStart = () => fill(actionMsg);


  // The confirmation lists every parameter that changes, the controller's value now → the designed one.
  function confirmApply() {
    const loop = page.loop;
    const g = loop?.gains;
    if (!g) return;
    fill(actionMsg);
    const diff = changes(loop.current_gains, g);
    const changed = diff.filter((d) => d.changed);
    const same = diff.filter((d) => !d.changed);
    fill(applyBox, h("div", { class: "confirm", id: "apply-dialog" },
      h("p", {}, `Write these gains to the controller of ${id}?`),
      h("table", { class: "changes", id: "apply-changes" },
        h("thead", {}, h("tr", {}, h("th", {}, ""), h("th", { class: "num" }, "now"), h("th", {}, ""),
          h("th", { class: "num" }, "new"))),
        h("tbody", {}, changed.map((d) => h("tr", { "data-param": d.key },
          h("th", {}, paramLabel(d.label, d.unit, unitsOf(loop))), h("td", { class: "num old" }, d.before === undefined ? "unknown" : paramText(d.key, d.before, d.unit)),
          h("td", { class: "arrow" }, "→"), h("td", { class: "num new" }, paramText(d.key, d.after, d.unit)))))),
      same.length ? h("p", { class: "muted small" }, `unchanged: ${same.map((d) => `${d.label} = ${paramText(d.key, d.after, d.unit)}`).join(", ")}`) : null,
      loop.current_gains ? null : h("p", { class: "muted small" }, "The controller's gains have not been read yet."),
      h("div", { class: "buttons" },
        h("button", { type: "button", class: "primary", id: "apply-confirm", onclick: () => {
          if (pending.has("apply")) return;
          fill(applyBox);
          // Settled when the apply is answered and the loop's status read after it is shown.
          pending.run("apply", async () => {
            const body = loop?.session ? { session: loop.session } : {};
            const answer = await post(`/loops/${esc(id)}/apply`, body);
            fill(actionMsg, h("div", { class: "alert ok", id: "apply-done" },
              `Gains of session ${String(answer?.session || "").slice(0, 8)} written to the controller.`));
            onApplied(await get(`/loops/${esc(id)}`));
          }, null, (err) => notify(err, actionMsg));
        } }, "Confirm"),
        h("button", { type: "button", class: "ghost", id: "apply-cancel", onclick: () => fill(applyBox) }, "Cancel"))));
  }

  function update(loop) {
    const operate = canOperate();
    pending.settle(loop);
    const tuning = pending.has("tune") ? "the TUNE request is under way" : "";
    form.setEnabled(operate && !loop.tbsy && !tuning, !operate ? "needs an operator token" : loop.tbsy ? "the loop is tuning" : tuning);
    tbrk.disabled = !(operate && loop.tbsy) || pending.has("tbrk");
    tbrk.title = !operate ? "needs an operator token" : pending.has("tbrk") ? "the abort is under way"
      : loop.tbsy ? "abort the experiment and restore the loop" : "nothing runs";
    const gains = loop.pending_gains && !loop.restore; // the daemon writes nothing to a loop not handed back
    apply.disabled = !(operate && !loop.tbsy && gains) || pending.has("apply");
    if (loop.restore) form.setEnabled(false, "the loop is not handed back yet (LOOP NOT RESTORED)");
    apply.title = !operate ? "needs an operator token" : pending.has("apply") ? "the gains are being written"
      : loop.tbsy ? "the loop is tuning"
      : loop.restore ? "the loop is not handed back yet"
      : !gains ? "no new gains to apply" : "write the new gains to the controller";
    if (apply.disabled) fill(applyBox);
    roleNote.textContent = operate ? "" : `Logged in with a ${me.role || "viewer"} token: you can watch, not act.`;
  }

  return {
    node,
    update,
    setDefaults: (loop) => form.setDefaults(loop),
    // Start a tuning with the form as it is (its fields hold the loop's defaults unless the operator changed them):
    // the same request, checks and error messages as pressing TUNE.
    tune: () => form.node.requestSubmit(),
    tunable: () => !form.button.disabled,
  };
}

// The TUNE form: controller, amp, hysteresis, phase, Ms, apply; only filled fields are sent (others: loop default).
// `pending`: the card's commands (a TUNE is one of them while it is sent and until the state shows its session).
function tuneForm(id, pending) {
  const fields = {
    controller: h("select", { name: "controller", id: "f-controller" }, h("option", { value: "PI" }, "PI"), h("option", { value: "PID" }, "PID")),
    amp: h("input", { name: "amp", id: "f-amp", type: "number", step: "any", inputmode: "decimal" }),
    hysteresis: h("input", { name: "hysteresis", id: "f-hysteresis", type: "number", step: "any", placeholder: "auto (3σ of noise)" }),
    phase: h("input", { name: "phase", id: "f-phase", type: "number", step: "any" }),
    ms: h("input", { name: "ms", id: "f-ms", type: "number", step: "any" }),
    apply: h("select", { name: "apply", id: "f-apply" }, h("option", { value: "" }, "loop default"),
      h("option", { value: "true" }, "yes, on success"), h("option", { value: "false" }, "no, I apply them")),
  };
  // Disabled until the loop's status is known (and the form holds its defaults): see setEnabled.
  const button = h("button", { type: "submit", class: "primary", id: "tune", disabled: true }, "TUNE");
  const row = (label, field, unit, hint) => h("label", { class: "field", "data-field": field.name },
    h("span", { class: "label" }, label), field, h("span", { class: "unit", "data-unit": field.name }, unit || ""), hint ? h("span", { class: "hint" }, hint) : null);
  const obj = { onError: null, onStart: null };
  const node = h("form", { class: "tune-form", id: "tune-form", novalidate: true, onsubmit: (ev) => {
    ev.preventDefault();
    if (pending.has("tune")) return; // Enter in a field, or "Tune now", while a TUNE is under way
    for (const f of Object.values(fields)) f.closest(".field").classList.remove("invalid");
    obj.onStart?.();
    const body = {};
    if (fields.controller.value) body.controller = fields.controller.value;
    for (const k of ["amp", "hysteresis", "phase", "ms"]) {
      const raw = fields[k].value.trim();
      if (raw !== "") body[k] = Number(raw);
      else if (fields[k].validity.badInput) body[k] = fields[k].value; // let the API name it
    }
    if (fields.apply.value) body.apply = fields.apply.value === "true";
    // Settled once the loop's state names the new session (tuning, or already ended): until then the state the
    // page holds may still be the idle one from before the TUNE.
    pending.run("tune", () => post(`/loops/${esc(id)}/tune`, body), (answer) => (loop) => loop.session === answer.session,
      (err) => {
        if (err instanceof ApiError) {
          for (const f of err.fields) fields[f]?.closest(".field").classList.add("invalid");
        }
        obj.onError?.(err);
      });
  } },
  row("Controller", fields.controller, ""),
  row("Relay amplitude", fields.amp, "MV"),
  row("Hysteresis", fields.hysteresis, "PV"),
  row("Phase lag", fields.phase, "°", "90–170"),
  row("Ms", fields.ms, "", "1.05–4"),
  row("Write gains", fields.apply, ""),
  h("div", { class: "buttons" }, button));
  obj.node = node;
  obj.button = button;
  obj.setEnabled = (on, why) => {
    button.disabled = !on;
    button.title = why || "start the relay experiment";
    for (const f of Object.values(fields)) f.disabled = !canOperate();
  };
  obj.setDefaults = (loop) => {
    const d = loop.defaults;
    const u = unitsOf(loop);
    $("[data-unit=amp]", node).textContent = u.mv || "MV";
    $("[data-unit=hysteresis]", node).textContent = u.pv || "PV";
    fields.controller.value = d.controller;
    fields.amp.value = d.amp;
    fields.hysteresis.value = d.hysteresis ?? "";
    fields.phase.value = d.phase;
    fields.ms.value = d.ms;
    fields.apply.value = d.apply ? "true" : "false";
  };
  return obj;
}

// The card's commands under way, by name ("tune", "tbrk", "apply"): each is pending from its press until its
// request is answered and, where the answer's effect reaches the page as a later loop state, until that state is
// the page's (`settle`). Any change redraws the page (`redraw`), so every button shows it at once.
function commands(redraw) {
  const waiting = new Map(); // name → null while the request runs, then the test a loop state must pass
  const has = (name) => waiting.has(name);
  const done = (name) => { waiting.delete(name); redraw(); };
  return {
    has,
    // `send()` makes the request; `until(answer)`, if given, the test of the state that settles it; `failed(err)`
    // shows why it was refused (then it is settled at once).
    async run(name, send, until, failed) {
      waiting.set(name, null);
      redraw();
      let answer;
      try {
        answer = await send();
      } catch (err) {
        failed(err);
        return done(name);
      }
      if (!until) return done(name);
      waiting.set(name, until(answer));
      redraw(); // settled at once if the state came before the answer
    },
    settle(loop) {
      for (const [name, test] of waiting) if (test && test(loop)) waiting.delete(name);
    },
  };
}
