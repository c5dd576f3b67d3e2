//! The keyboard, the same in the native viewer and the webplayer. Keys are named by
//! their physical position as the DOM's `KeyboardEvent.code` names them ("KeyW",
//! "ArrowUp", "PageDown"); winit's `KeyCode` variants carry the same names, so the
//! viewer passes `format!("{code:?}")`.

use std::collections::HashSet;

use crate::fly::FlyInput;

/// What a key press does besides flying.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Action {
    /// G: overlay the mesh's edges, or not.
    ToggleWireframe,
    /// L: tint each mesh level, or not.
    ToggleLodColours,
    /// H: show the HUD, or hide it.
    ToggleHud,
    /// Escape: close the viewer (the webplayer ignores it).
    Quit,
}

#[cfg(feature = "render")]
impl Action {
    /// Applies a toggle to the renderer's settings and the HUD's visibility (`Quit` is the
    /// front end's to act on).
    pub fn toggle(self, settings: &mut crate::render::renderer::RenderSettings, hud: &mut bool) {
        match self {
            Self::ToggleWireframe => settings.wireframe = !settings.wireframe,
            Self::ToggleLodColours => settings.lod_colours = !settings.lod_colours,
            Self::ToggleHud => *hud = !*hud,
            Self::Quit => {}
        }
    }
}

/// One line of help for the HUD.
pub const CONTROLS: &str = "WASD/arrows fly  Q/E or PgDn/PgUp down/up  drag look  wheel speed  G wire  L LODs  H HUD";

const FORWARD: &[&str] = &["KeyW", "ArrowUp"];
const BACK: &[&str] = &["KeyS", "ArrowDown"];
const RIGHT: &[&str] = &["KeyD", "ArrowRight"];
const LEFT: &[&str] = &["KeyA", "ArrowLeft"];
const UP: &[&str] = &["KeyE", "PageUp"];
const DOWN: &[&str] = &["KeyQ", "PageDown"];

/// The keys held down, and those pressed since the last frame.
#[derive(Clone, Debug, Default)]
pub struct Keys {
    held: HashSet<String>,
    /// Pressed since the last [`Keys::fly`]: a key pressed and released between two frames
    /// (a quick tap, or any press while a frame stalls) still flies for one frame.
    pressed: HashSet<String>,
}

impl Keys {
    /// A key went down; the action it asks for, once per press (not on auto-repeat).
    pub fn press(&mut self, code: &str, repeat: bool) -> Option<Action> {
        self.held.insert(code.to_owned());
        self.pressed.insert(code.to_owned());
        if repeat {
            return None;
        }
        match code {
            "KeyG" => Some(Action::ToggleWireframe),
            "KeyL" => Some(Action::ToggleLodColours),
            "KeyH" => Some(Action::ToggleHud),
            "Escape" => Some(Action::Quit),
            _ => None,
        }
    }

    /// A key went up.
    pub fn release(&mut self, code: &str) {
        self.held.remove(code);
    }

    /// Every key up: the window lost the keyboard, so releases will not arrive.
    pub fn release_all(&mut self) {
        self.held.clear();
        self.pressed.clear();
    }

    /// Which way the keys ask to fly this frame: those held, and those pressed since the
    /// last frame even if already released. Called once a frame.
    pub fn fly(&mut self) -> FlyInput {
        let axis = |plus: &[&str], minus: &[&str]| {
            let held = |codes: &[&str]| codes.iter().any(|c| self.held.contains(*c) || self.pressed.contains(*c));
            f64::from(u8::from(held(plus))) - f64::from(u8::from(held(minus)))
        };
        let input = FlyInput { forward: axis(FORWARD, BACK), right: axis(RIGHT, LEFT), up: axis(UP, DOWN) };
        self.pressed.clear();
        input
    }

    /// Keys a page would otherwise scroll with: the player keeps them for flying.
    pub fn is_navigation(code: &str) -> bool {
        [FORWARD, BACK, RIGHT, LEFT, UP, DOWN].iter().any(|keys| keys[1..].contains(&code)) || code == "Space"
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn letters_and_arrows_fly_alike_and_toggles_fire_once() {
        let mut keys = Keys::default();
        assert_eq!(keys.press("ArrowUp", false), None);
        assert_eq!(keys.press("PageDown", false), None);
        assert_eq!(keys.fly(), FlyInput { forward: 1.0, right: 0.0, up: -1.0 });
        keys.release("ArrowUp");
        keys.release("PageDown");
        keys.press("KeyW", false);
        keys.press("KeyE", false);
        keys.press("KeyA", false);
        assert_eq!(keys.fly(), FlyInput { forward: 1.0, right: -1.0, up: 1.0 });
        // Opposite keys cancel.
        keys.press("ArrowDown", false);
        assert_eq!(keys.fly().forward, 0.0);
        assert_eq!(keys.press("KeyG", false), Some(Action::ToggleWireframe));
        assert_eq!(keys.press("KeyG", true), None);
        assert_eq!(keys.press("KeyH", false), Some(Action::ToggleHud));
        assert_eq!(keys.press("Escape", false), Some(Action::Quit));
        assert!(Keys::is_navigation("PageUp") && Keys::is_navigation("ArrowLeft") && !Keys::is_navigation("KeyW"));
    }

    #[test]
    fn a_tap_between_two_frames_flies_for_one_frame() {
        let mut keys = Keys::default();
        keys.press("KeyW", false);
        keys.release("KeyW");
        assert_eq!(keys.fly().forward, 1.0, "pressed and released before the frame");
        assert_eq!(keys.fly().forward, 0.0, "only once");
        // A tap of the opposite key while one is held cancels for that frame only.
        keys.press("KeyD", false);
        keys.press("KeyA", false);
        keys.release("KeyA");
        assert_eq!(keys.fly().right, 0.0);
        assert_eq!(keys.fly().right, 1.0);
        // Losing the keyboard forgets taps too.
        keys.press("KeyS", false);
        keys.release("KeyS");
        keys.release_all();
        assert_eq!(keys.fly(), FlyInput::default());
    }
}
