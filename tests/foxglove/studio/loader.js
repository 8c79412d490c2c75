// The small loader a web page needs to run the app @foxglove/studio-base 1.48.0 ships
// prebuilt (the open-source Foxglove Studio's last release), without a bundler: the app's
// settings and its layouts in memory, the layout of ?layoutUrl= seeded under ?layoutId=,
// which the app's own deep link then selects; ?ds=remote-file&ds.url=... opens a recording
// served with HTTP range requests.  Written for the viewer test; not part of the testbench.
(async function main() {
  const S = window; // UMD exports are copied onto window
  const params = new URLSearchParams(location.search);
  const layoutUrl = params.get("layoutUrl") || "layout.json";
  const layoutId = params.get("layoutId") || "etar";

  // ---- IAppConfiguration (in memory, defaults chosen to avoid dialogs/telemetry)
  const settings = {
    "telemetry.telemetryEnabled": false,
    "telemetry.crashReportingEnabled": false,
    "ui.open-dialog-startup": false,
    "launchPreference": "web",
    "hideSignInPrompt": true,
    "updates.enabled": false,
    "colorScheme": params.get("colorScheme") || "dark",
    "timezone": "UTC",
    "messageRate": 60,
  };
  const listeners = new Map();
  const appConfiguration = {
    get: (k) => settings[k],
    set: async (k, v) => { settings[k] = v; (listeners.get(k) || []).forEach((cb) => cb(v)); },
    addChangeListener: (k, cb) => { if (!listeners.has(k)) listeners.set(k, new Set()); listeners.get(k).add(cb); },
    removeChangeListener: (k, cb) => { listeners.get(k)?.delete(cb); },
  };

  // ---- ILayoutStorage (in memory, seeded)
  const layoutData = await (await fetch(layoutUrl)).json();
  const now = new Date().toISOString();
  const store = new Map(); // key ns + "\0" + id
  const key = (ns, id) => ns + "\u0000" + id;
  store.set(key("local", layoutId), {
    id: layoutId, name: params.get("layoutName") || "etar", permission: "CREATOR_WRITE",
    baseline: { data: layoutData, savedAt: now }, working: undefined, syncInfo: undefined,
  });
  const layoutStorage = {
    async list(ns) { return [...store.entries()].filter(([k]) => k.startsWith(ns + "\u0000")).map(([, v]) => v); },
    async get(ns, id) { return store.get(key(ns, id)); },
    async put(ns, layout) { store.set(key(ns, layout.id), layout); return layout; },
    async delete(ns, id) { store.delete(key(ns, id)); },
    async migrateUnnamespacedLayouts() {},
    async importLayouts() {},
  };

  const dataSources = [
    new S.RemoteDataSourceFactory(),
    new S.McapLocalDataSourceFactory(),
    new S.FoxgloveWebSocketDataSourceFactory(),
    new S.Ros1LocalBagDataSourceFactory(),
  ];

  // Suppress the per-panel "Open settings to configure..." onboarding tooltips (?tooltips=1 keeps them).
  if (!params.get("tooltips")) {
    localStorage.setItem("studio.profile-data", JSON.stringify({ onboarding: { settingsTooltipShownForPanelTypes:
      ["3D", "Plot", "StateTransitions", "RosOut", "RawMessages", "Table", "ImageViewPanel", "map", "Indicator", "Gauge"] } }));
  }
  S.overwriteFetch();
  await S.waitForFonts();
  await S.initI18n();
  const h = S.React.createElement;
  S.ReactDOM.render(
    h(S.App, {
      deepLinks: [location.href],
      appConfiguration, layoutStorage, dataSources,
      extensionLoaders: [],
      enableLaunchPreferenceScreen: false,
      enableGlobalCss: true,
      extraProviders: [],
    }),
    document.getElementById("root"),
  );
  window.__fgLoaderDone = Date.now();
})().catch((e) => { console.error("loader failed", e); window.__fgLoaderError = String(e && e.stack || e); });
