// The landing page (index.html, served at /): the server's rigs and live channels, with
// links to the viewer, overlay and performer studio, and to the API docs. The page's own
// ?token= goes to the REST calls as a Bearer header and on to every link it builds.

const token = new URL(window.location.href).searchParams.get("token") || null;
const headers = token !== null ? { Authorization: `Bearer ${token}` } : {};

/** A link to one of the server's pages, carrying the page's token. */
export function pageUrl(path, query, pageToken = token) {
  const q = new URLSearchParams(query);
  if (pageToken !== null) q.set("token", pageToken);
  const text = q.toString();
  return text ? `${path}?${text}` : path;
}

/** What a refused request needs, in words (the server's problem body names the cause). */
function refusal(what, status, problem) {
  const detail = problem.detail || `HTTP ${status}`;
  if (status === 401 && token === null) {
    // Said once for both lists: the same words dedupe.
    return "This server requires a token: open this page as /?token=TOKEN with a token " +
      "holding the viewer role (or admin).";
  }
  if (status === 401) return `The token is not accepted (401 ${problem.code || "unauthorized"}): ${detail}`;
  if (status === 403) return `The token may not list ${what} (403 ${problem.code || "forbidden"}): ${detail}`;
  return `Listing ${what} failed (${status} ${problem.code || ""}): ${detail}`;
}

class Refused extends Error {}

async function getJson(path, what) {
  let response;
  try {
    response = await fetch(path, { headers });
  } catch (err) {
    throw new Refused(`The server did not answer ${path}: ${err.message}`);
  }
  if (response.ok) return response.json();
  const problem = await response.json().catch(() => ({}));
  throw new Refused(refusal(what, response.status, problem));
}

function element(tag, props = {}, children = []) {
  const node = Object.assign(document.createElement(tag), props);
  node.append(...children);
  return node;
}

function link(text, href) {
  return element("a", { href, textContent: text });
}

function fill(table, rows, emptyText) {
  const body = table.tBodies[0];
  if (rows.length === 0) {
    const columns = table.tHead.rows[0].cells.length;
    rows = [element("tr", {}, [element("td", { colSpan: columns, className: "empty", textContent: emptyText })])];
  }
  body.replaceChildren(...rows);
}

function size(bytes) {
  if (bytes < 1024 * 1024) return `${(bytes / 1024).toFixed(1)} KiB`;
  return `${(bytes / 1024 / 1024).toFixed(1)} MiB`;
}

function when(seconds) {
  return new Date(seconds * 1000).toISOString().replace("T", " ").slice(0, 16) + " UTC";
}

const state = { rigs: [], channels: [] };
const watchRig = document.getElementById("watch-rig");
const performChannel = document.getElementById("perform-channel");
const performer = document.getElementById("performer");

const FORMATS = { gltf: "glTF", vrm0: "VRM 0.x", vrm1: "VRM 1.0" };

/** A rig's character file and who is shown it under its licence (GET /v1/rigs). */
export function characterCell(character) {
  if (!character) return element("td", { className: "character", textContent: "—" });
  const name = character.name ? ` “${character.name}”` : "";
  const who = character.shown_to === "everyone"
    ? (character.rights_holder ? "shown to everyone (rights holder)" : "shown to everyone")
    : "token holders only (licence)";
  return element("td", {
    className: `character ${character.shown_to === "everyone" ? "open" : "held"}`,
    textContent: `${FORMATS[character.format] || character.format}${name} · ${who}`,
    title: character.licence_note || "",
  });
}

function renderRigs() {
  const rows = state.rigs.map((rig) => {
    const perform = { channel: performChannel.value || "stage", rig: rig.id, performer: performer.value || "performer" };
    return element("tr", {}, [
      element("td", { className: "id", textContent: rig.id }),
      characterCell(rig.character),
      element("td", { textContent: size(rig.size) }),
      element("td", { textContent: when(rig.modified) }),
      element("td", { className: "links" }, [
        link("viewer", pageUrl("viewer", { rig: rig.id })),
        link("overlay", pageUrl("overlay", { rig: rig.id })),
        link("perform", pageUrl("perform", perform)),
      ]),
    ]);
  });
  fill(document.getElementById("rigs"), rows, "No rigs stored yet: upload one with facecast rigs put.");
}

function renderChannels() {
  const rows = state.channels.map((channel) => {
    // The rig a viewer of this channel sees: the one chosen above, else the one most watched.
    const watched = Object.entries(channel.viewers_per_rig || {}).sort((a, b) => b[1] - a[1]);
    const rig = watchRig.value || (watched.length ? watched[0][0] : "demo");
    return element("tr", {}, [
      element("td", { className: "id", textContent: channel.name }),
      element("td", { className: channel.publisher ? "live" : "", textContent: channel.publisher ? "live" : "none" }),
      element("td", { textContent: String(channel.viewers) }),
      element("td", { className: "links" }, [
        link("viewer", pageUrl("viewer", { channel: channel.name, rig })),
        link("overlay", pageUrl("overlay", { channel: channel.name, rig })),
      ]),
    ]);
  });
  fill(document.getElementById("channels"), rows, "No live channels: a publisher (the performer studio, facecast perform or publish) opens one.");
}

function showError(message) {
  const box = document.getElementById("error");
  box.textContent = message;
  box.hidden = false;
}

async function main() {
  document.getElementById("docs-link").href = pageUrl("docs", {});
  document.getElementById("demo-link").href = pageUrl("viewer", {});
  const [rigs, channels] = await Promise.allSettled([
    getJson("v1/rigs", "rigs"),
    getJson("v1/channels", "channels"),
  ]);
  const errors = [];
  if (rigs.status === "fulfilled") state.rigs = rigs.value.rigs;
  else errors.push(rigs.reason.message);
  if (channels.status === "fulfilled") state.channels = channels.value.channels;
  else errors.push(channels.reason.message);
  if (errors.length) showError([...new Set(errors)].join("\n"));
  watchRig.replaceChildren(
    element("option", { value: "", textContent: "most watched" }),
    ...state.rigs.map((rig) => element("option", { value: rig.id, textContent: rig.id })),
  );
  renderRigs();
  renderChannels();
  if (rigs.status === "rejected") fill(document.getElementById("rigs"), [], "Not listed (see above).");
  if (channels.status === "rejected") fill(document.getElementById("channels"), [], "Not listed (see above).");
  window.facecastLanding = { loaded: true, errors, rigs: state.rigs.length, channels: state.channels.length };
}

watchRig.addEventListener("change", renderChannels);
performChannel.addEventListener("input", renderRigs);
performer.addEventListener("input", renderRigs);
main().catch((err) => {
  showError(`The page failed: ${err.message}`);
  window.facecastLanding = { loaded: true, errors: [err.message], rigs: 0, channels: 0 };
});
