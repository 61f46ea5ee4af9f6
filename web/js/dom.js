// The two DOM helpers every view uses.

/** The element with this id. */
export const $ = (id) => document.getElementById(id);

/** Fill a list (<ul>) with one <li> per text; an empty array empties it. */
export function showList(id, texts) {
  $(id).replaceChildren(...texts.map((text) => Object.assign(document.createElement("li"), { textContent: text })));
}
