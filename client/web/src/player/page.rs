//! The page: its elements, the URL's parameters, the status line.

use super::*;

/// What the page asked for in its URL.
pub(super) struct Params {
    pub(super) archive: String,
    pub(super) camera: Option<(DVec3, DVec3)>,
    /// `at=LON,LAT,HEIGHT` with `heading=` and `pitch=` (degrees; CesiumJS's conventions).
    pub(super) pose: Option<terrastream_client::fly::Pose>,
    pub(super) backends: wgpu::Backends,
    pub(super) hud: bool,
    /// Web Workers that decode tiles (`workers=N`; 0: on the page's thread). Default:
    /// one fewer than the machine's cores, 1 to 4.
    pub(super) workers: Option<usize>,
    /// Frames of the benchmark flight (`flight=N`).
    pub(super) flight: Option<usize>,
    /// The flat plate even for an archive that says where it lies (`flat=1`; implied by
    /// `camera=`, which is in world units): else the globe.
    pub(super) flat: bool,
    /// `sun=AZIMUTH,ELEVATION` (degrees), as `render --sun`.
    pub(super) sun: Option<DVec3>,
    /// On the globe, the physically based sky and aerial perspective (`atmosphere=0`: a
    /// plain haze, as `render --no-atmosphere`).
    pub(super) atmosphere: bool,
    /// On the globe, the built-in whole-Earth picture on its heights beyond the data
    /// (`earth=0`: plain ground, as `render --no-earth`).
    pub(super) earth: bool,
}

/// The page's elements.
pub(super) struct Page {
    pub(super) window: Window,
    pub(super) canvas: HtmlCanvasElement,
    pub(super) hud: Option<HtmlElement>,
    pub(super) status: Option<HtmlElement>,
}

impl Page {
    pub(super) fn find() -> Result<Self, String> {
        let window = web_sys::window().ok_or("no window")?;
        let document = window.document().ok_or("no document")?;
        let canvas = element(&document, "terrain")
            .ok_or("the page has no <canvas id=\"terrain\">")?
            .dyn_into::<HtmlCanvasElement>()
            .map_err(|_| "#terrain is not a <canvas>")?;
        let hud = element(&document, "hud").and_then(|e| e.dyn_into().ok());
        let status = element(&document, "status").and_then(|e| e.dyn_into().ok());
        Ok(Self { window, canvas, hud, status })
    }

    /// Shows `text` in the status box (`None` hides it); `error` styles it as one.
    pub(super) fn status(&self, text: Option<&str>, error: bool) {
        let Some(status) = &self.status else { return };
        match text {
            Some(text) => {
                if status.text_content().as_deref() != Some(text) {
                    status.set_text_content(Some(text));
                }
                status.set_hidden(false);
            }
            None => status.set_hidden(true),
        }
        let _ = status.class_list().toggle_with_force("error", error);
    }

    pub(super) fn now_ms(&self) -> f64 {
        self.window.performance().map_or(0.0, |p| p.now())
    }

    /// The canvas's size in device pixels, at least 1, at most `max` a side.
    pub(super) fn canvas_size(&self, max: u32) -> (u32, u32) {
        let ratio = self.window.device_pixel_ratio().max(0.5);
        // In range: clamped to [1, max] before the cast.
        #[allow(clippy::cast_possible_truncation)]
        let side = |css: i32| (f64::from(css.max(1)) * ratio).round().clamp(1.0, f64::from(max)) as u32;
        (side(self.canvas.client_width()), side(self.canvas.client_height()))
    }
}

pub(super) fn element(document: &Document, id: &str) -> Option<web_sys::Element> {
    document.get_element_by_id(id)
}

pub(super) fn params(window: &Window) -> Result<Params, String> {
    let location = window.location();
    let href = location.href().map_err(js_text)?;
    let query = web_sys::UrlSearchParams::new_with_str(&location.search().map_err(js_text)?).map_err(js_text)?;
    let meta = window
        .document()
        .and_then(|d| d.query_selector("meta[name=terrastream-archive]").ok().flatten())
        .and_then(|m| m.get_attribute("content"))
        .filter(|c| !c.trim().is_empty());
    let archive = query.get("archive").filter(|a| !a.trim().is_empty()).or(meta).ok_or(
        "No archive to show: open this page as player.html?archive=<URL of a .tspack file> \
         (the URL may be relative to the page).",
    )?;
    let archive = web_sys::Url::new_with_base(archive.trim(), &href)
        .map_err(|_| format!("The archive address {archive:?} is not a valid URL."))?
        .href();
    let camera = match query.get("camera") {
        Some(text) => Some(parse_camera(&text)?),
        None => None,
    };
    let degrees = |name: &str, default: f64| match query.get(name) {
        None => Ok(default),
        Some(v) => v.trim().parse::<f64>().map_err(|_| format!("{name}={v:?}: a number of degrees")),
    };
    let pose = match query.get("at") {
        Some(at) => {
            Some(terrastream_client::fly::Pose::parse(&at, degrees("heading", 0.0)?, degrees("pitch", -30.0)?)?)
        }
        None => None,
    };
    let backends = match query.get("backend").as_deref() {
        None | Some("" | "auto") => wgpu::Backends::BROWSER_WEBGPU | wgpu::Backends::GL,
        Some("webgpu") => wgpu::Backends::BROWSER_WEBGPU,
        Some("webgl2" | "webgl" | "gl") => wgpu::Backends::GL,
        Some(other) => return Err(format!("Unknown backend {other:?}: use webgpu, webgl2 or auto.")),
    };
    let workers = query.get("workers").and_then(|w| w.parse().ok());
    let flight = match query.get("flight") {
        None => None,
        Some(n) => {
            Some(n.parse().ok().filter(|&n| n >= 2).ok_or(format!("flight={n:?}: a number of frames, 2 or more"))?)
        }
    };
    // A switch: None where the page does not give it; `meaning` names its two values.
    let switch = |name: &str, meaning: &str| match query.get(name).as_deref() {
        None => Ok(None),
        Some("" | "1" | "true" | "yes") => Ok(Some(true)),
        Some("0" | "false" | "no") => Ok(Some(false)),
        Some(other) => Err(format!("{name}={other:?}: {meaning}")),
    };
    let flat = switch("flat", "1 (the flat plate) or 0 (the globe)")?.unwrap_or(false) || camera.is_some();
    let hud = query.get("hud").as_deref() != Some("0");
    let sun = query.get("sun").map(|s| terrastream_client::globe::parse_sun(&s)).transpose()?;
    let on = |name: &str| switch(name, "1 (on) or 0 (off)").map(|v| v.unwrap_or(true));
    let (atmosphere, earth) = (on("atmosphere")?, on("earth")?);
    Ok(Params { archive, camera, pose, backends, hud, workers, flight, flat, sun, atmosphere, earth })
}

pub(super) fn parse_camera(text: &str) -> Result<(DVec3, DVec3), String> {
    let v: Vec<f64> = text
        .split(',')
        .map(|s| s.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("camera={text:?}: expected six numbers ex,ey,ez,tx,ty,tz"))?;
    match v[..] {
        [ex, ey, ez, tx, ty, tz] if v.iter().all(|x| x.is_finite()) => {
            Ok((DVec3::new(ex, ey, ez), DVec3::new(tx, ty, tz)))
        }
        _ => Err(format!("camera={text:?}: expected six numbers ex,ey,ez,tx,ty,tz")),
    }
}

pub(super) fn js_text(v: JsValue) -> String {
    v.as_string()
        .or_else(|| v.dyn_ref::<js_sys::Error>().map(|e| String::from(e.message())))
        .unwrap_or_else(|| format!("{v:?}"))
}
