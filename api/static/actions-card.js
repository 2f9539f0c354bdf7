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
// an apply (the result card then shows the session as applied).
export function actionsCard(page, onApplied) {
  const id = page.id;
  const node = h("section", { class: "card actions", id: "actions" });
  // The form, built once (so typing is not lost on updates); its defaults from the loop when the API gives them.
  const form = tuneForm(id, () => page.loop);
  const actionMsg = h("div", { class: "form-msg", id: "action-msg" });
  const tbrk = h("button", { type: "button", class: "danger", id: "tbrk", onclick: async () => {
    fill(actionMsg);
    try { await post(`/loops/${esc(id)}/break`); } catch (err) { notify(err, actionMsg); }
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
        h("button", { type: "button", class: "primary", id: "apply-confirm", onclick: async () => {
          fill(applyBox);
          try {
            const body = loop?.session ? { session: loop.session } : {};
            const answer = await post(`/loops/${esc(id)}/apply`, body);
            fill(actionMsg, h("div", { class: "alert ok", id: "apply-done" },
              `Gains of session ${String(answer?.session || "").slice(0, 8)} written to the controller.`));
            onApplied(await get(`/loops/${esc(id)}`));
          } catch (err) { notify(err, actionMsg); }
        } }, "Confirm"),
        h("button", { type: "button", class: "ghost", id: "apply-cancel", onclick: () => fill(applyBox) }, "Cancel"))));
  }

  function update(loop) {
    const operate = canOperate();
    form.setEnabled(operate && !loop.tbsy, !operate ? "needs an operator token" : loop.tbsy ? "the loop is tuning" : "");
    tbrk.disabled = !(operate && loop.tbsy);
    tbrk.title = !operate ? "needs an operator token" : loop.tbsy ? "abort the experiment and restore the loop" : "nothing runs";
    const pending = loop.pending_gains && !loop.restore; // the daemon writes nothing to a loop not handed back
    apply.disabled = !(operate && !loop.tbsy && pending);
    if (loop.restore) form.setEnabled(false, "the loop is not handed back yet (LOOP NOT RESTORED)");
    apply.title = !operate ? "needs an operator token" : loop.tbsy ? "the loop is tuning"
      : loop.restore ? "the loop is not handed back yet"
      : !pending ? "no new gains to apply" : "write the new gains to the controller";
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
function tuneForm(id, getLoop) {
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
  const node = h("form", { class: "tune-form", id: "tune-form", novalidate: true, onsubmit: async (ev) => {
    ev.preventDefault();
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
    button.disabled = true;
    try {
      await post(`/loops/${esc(id)}/tune`, body);
    } catch (err) {
      if (err instanceof ApiError) {
        for (const f of err.fields) fields[f]?.closest(".field").classList.add("invalid");
      }
      obj.onError?.(err);
      button.disabled = Boolean(getLoop()?.tbsy) || !canOperate();
    }
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