//! Headless Chromium driven through chromedriver (WebDriver), for the tests of the
//! webplayer and of the ecosystem's browser clients (MapLibre GL JS).

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use base64::Engine as _;
use serde_json::{Value, json};

/// Debian's Chromium.
pub const CHROMIUM: &str = "/usr/bin/chromium";
/// Debian's chromedriver.
pub const CHROMEDRIVER: &str = "/usr/bin/chromedriver";

/// Flags that give headless Chromium WebGPU on SwiftShader's Vulkan (and compose its
/// canvas into screenshots). WebGL2 is not available with them.
pub const WEBGPU_FLAGS: &[&str] = &[
    "--enable-unsafe-webgpu",
    "--enable-features=Vulkan",
    "--use-angle=vulkan",
    "--use-vulkan=swiftshader",
    "--enable-unsafe-swiftshader",
];
/// WebGL2 on SwiftShader (ANGLE's default in headless mode).
pub const WEBGL_FLAGS: &[&str] = &["--enable-unsafe-swiftshader"];

/// What the browser tests need and this machine lacks.
pub fn missing() -> Vec<&'static str> {
    let mut missing = Vec::new();
    if !Path::new(CHROMIUM).exists() {
        missing.push("chromium (apt-get install chromium)");
    }
    if !Path::new(CHROMEDRIVER).exists() {
        missing.push("chromedriver (apt-get install chromium-driver)");
    }
    missing
}

/// True when nothing is `missing`; otherwise fails, unless `TERRASTREAM_ALLOW_NO_BROWSER`
/// is set (then says loudly that the `what` tests are skipped, and returns false).
pub fn skip_or_fail(what: &str, missing: &[&str]) -> bool {
    if missing.is_empty() {
        return true;
    }
    let list = missing.join(", ");
    assert!(
        std::env::var_os("TERRASTREAM_ALLOW_NO_BROWSER").is_some(),
        "missing: {list}; the test command installs them (TERRASTREAM_ALLOW_NO_BROWSER=1 skips)"
    );
    eprintln!("\n!!!!! SKIPPING {what} TESTS: missing {list} (TERRASTREAM_ALLOW_NO_BROWSER is set) !!!!!\n");
    false
}

/// A child process killed on drop.
pub struct Process(pub Child);

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Waits until something listens on loopback `port`.
pub fn wait_for_port(port: u16, what: &str) {
    let start = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(start.elapsed() < Duration::from_secs(20), "{what} did not start on port {port}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// chromedriver on a loopback port.
pub struct Driver {
    _process: Process,
    port: u16,
}

impl Driver {
    /// Starts chromedriver.
    pub fn start() -> Self {
        let port = crate::nginx::free_port();
        let child = Command::new(CHROMEDRIVER)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("starting chromedriver");
        wait_for_port(port, "chromedriver");
        Self { _process: Process(child), port }
    }

    /// A WebDriver call; its `value`.
    pub fn call(&self, method: &str, path: &str, body: Option<Value>) -> Value {
        let (status, bytes) = crate::http::request(self.port, method, path, body.as_ref());
        let value: Value = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
        assert!(status == 200, "WebDriver {method} {path}: {status} {value}");
        value["value"].clone()
    }
}

/// A headless Chromium session, closed on drop.
pub struct Browser<'a> {
    driver: &'a Driver,
    session: String,
    _profile: tempfile::TempDir,
}

impl<'a> Browser<'a> {
    /// A session with a window of `size` CSS pixels (at scale 1) and extra `flags`.
    pub fn open(driver: &'a Driver, flags: &[&str], size: (u32, u32)) -> Self {
        let profile = tempfile::tempdir().unwrap();
        let mut args: Vec<String> = [
            "--headless=new",
            "--no-sandbox",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
            "--force-device-scale-factor=1",
        ]
        .iter()
        .map(ToString::to_string)
        .collect();
        args.push(format!("--user-data-dir={}", profile.path().display()));
        args.push(format!("--window-size={},{}", size.0, size.1));
        args.extend(flags.iter().map(ToString::to_string));
        let caps = json!({ "capabilities": { "alwaysMatch": {
            "browserName": "chrome",
            "goog:loggingPrefs": { "browser": "ALL" },
            "goog:chromeOptions": { "binary": CHROMIUM, "args": args },
        }}});
        let value = driver.call("POST", "/session", Some(caps));
        let session = value["sessionId"].as_str().expect("a session id").to_owned();
        Self { driver, session, _profile: profile }
    }

    /// A WebDriver call in this session.
    pub fn call(&self, method: &str, path: &str, body: Option<Value>) -> Value {
        self.driver.call(method, &format!("/session/{}{path}", self.session), body)
    }

    /// Loads `url`.
    pub fn goto(&self, url: &str) {
        self.call("POST", "/url", Some(json!({ "url": url })));
    }

    /// Runs `script` (a function body) in the page; what it returns.
    pub fn eval(&self, script: &str) -> Value {
        self.call("POST", "/execute/sync", Some(json!({ "script": script, "args": [] })))
    }

    /// Runs `script` (a function body that calls `arguments[0]` with its result) in the
    /// page and waits for the result.
    pub fn eval_async(&self, script: &str) -> Value {
        self.call("POST", "/execute/async", Some(json!({ "script": script, "args": [] })))
    }

    /// The browser console since the last call: (level, message).
    pub fn console(&self) -> Vec<(String, String)> {
        let logs = self.call("POST", "/se/log", Some(json!({ "type": "browser" })));
        logs.as_array()
            .into_iter()
            .flatten()
            .map(|l| (l["level"].as_str().unwrap_or("").to_owned(), l["message"].as_str().unwrap_or("").to_owned()))
            .collect()
    }

    /// A screenshot of the element `css`, decoded: (width, height, RGBA).
    pub fn screenshot(&self, css: &str) -> (u32, u32, Vec<u8>) {
        let element = self.call("POST", "/element", Some(json!({ "using": "css selector", "value": css })));
        let id = element.as_object().and_then(|o| o.values().next()).and_then(Value::as_str).unwrap().to_owned();
        let png = self.call("GET", &format!("/element/{id}/screenshot"), None);
        crate::golden::decode_png(&base64::engine::general_purpose::STANDARD.decode(png.as_str().unwrap()).unwrap())
    }

    /// Holds `key` (a WebDriver key value) down for `ms` milliseconds.
    pub fn hold_key(&self, key: &str, ms: u64) {
        let actions = json!({ "actions": [{ "type": "key", "id": "keyboard", "actions": [
            { "type": "keyDown", "value": key },
            { "type": "pause", "duration": ms },
            { "type": "keyUp", "value": key },
        ]}]});
        self.call("POST", "/actions", Some(actions));
    }

    /// Runs WebDriver input `sources` (key, pointer, wheel) tick by tick.
    pub fn act(&self, sources: Value) {
        self.call("POST", "/actions", Some(json!({ "actions": sources })));
    }

    /// A pointer (`kind`: mouse, touch) pressed at `from`, moved to `to` over `ms`,
    /// released (viewport pixels).
    pub fn drag(id: &str, kind: &str, from: (i64, i64), to: (i64, i64), ms: u64) -> Value {
        json!({ "type": "pointer", "id": id, "parameters": { "pointerType": kind }, "actions": [
            { "type": "pointerMove", "x": from.0, "y": from.1, "origin": "viewport", "duration": 0 },
            { "type": "pointerDown", "button": 0 },
            { "type": "pointerMove", "x": to.0, "y": to.1, "origin": "viewport", "duration": ms },
            { "type": "pointerUp", "button": 0 },
        ]})
    }
}

impl Drop for Browser<'_> {
    fn drop(&mut self) {
        let _ = crate::http::request(self.driver.port, "DELETE", &format!("/session/{}", self.session), None);
    }
}
