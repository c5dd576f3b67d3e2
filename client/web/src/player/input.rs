//! Keyboard, pointer and wheel: their state between frames and the page's listeners.

use super::*;

/// Keyboard, pointer and wheel state between frames.
#[derive(Default)]
pub(super) struct Input {
    pub(super) keys: Keys,
    /// Active pointers (mouse buttons held, fingers down): id -> last position.
    pub(super) pointers: HashMap<i32, (f64, f64)>,
    /// Distance between two fingers at the last move.
    pub(super) pinch: Option<f64>,
    /// Flight along the view asked for by pinching, in seconds at the current speed.
    pub(super) pinch_seconds: f64,
}

impl State {
    pub(super) fn key(&mut self, event: &KeyboardEvent, down: bool) {
        let code = event.code();
        if Keys::is_navigation(&code) {
            event.prevent_default();
        }
        if !down {
            self.input.keys.release(&code);
            return;
        }
        let action = self.input.keys.press(&code, event.repeat());
        if let (Some(action), Phase::Running { session, .. }) = (action, &mut self.phase) {
            let mut s = *session.renderer.settings();
            action.toggle(&mut s, &mut self.show_hud);
            session.renderer.set_view_settings(s);
            if let Some(hud) = &self.page.hud {
                hud.set_hidden(!self.show_hud);
            }
        }
    }

    pub(super) fn pointer(&mut self, event: &PointerEvent, kind: PointerKind) {
        let id = event.pointer_id();
        let at = (f64::from(event.client_x()), f64::from(event.client_y()));
        match kind {
            PointerKind::Down => {
                let _ = self.page.canvas.set_pointer_capture(id);
                let _ = self.page.canvas.focus();
                self.input.pointers.insert(id, at);
                self.input.pinch = None;
            }
            PointerKind::Up => {
                self.input.pointers.remove(&id);
                self.input.pinch = None;
            }
            PointerKind::Move => {
                let Some(last) = self.input.pointers.get(&id).copied() else { return };
                self.input.pointers.insert(id, at);
                let Phase::Running { fly, .. } = &mut self.phase else { return };
                match self.input.pointers.len() {
                    1 => fly.look(at.0 - last.0, at.1 - last.1),
                    2 => {
                        let mut points = self.input.pointers.values();
                        let (Some(a), Some(b)) = (points.next(), points.next()) else { return };
                        let distance = (a.0 - b.0).hypot(a.1 - b.1);
                        if let Some(before) = self.input.pinch {
                            // Spreading the fingers flies forward: 200 px is a second's flight.
                            self.input.pinch_seconds += (distance - before) / 200.0;
                        }
                        self.input.pinch = Some(distance);
                    }
                    _ => {}
                }
            }
        }
    }

    pub(super) fn wheel(&mut self, event: &WheelEvent) {
        event.prevent_default();
        // Pixels (mode 0): about 100 a notch; lines (mode 1): 3 a notch.
        let notches = match event.delta_mode() {
            0 => -event.delta_y() / 100.0,
            1 => -event.delta_y() / 3.0,
            _ => -event.delta_y(),
        };
        if let Phase::Running { fly, .. } = &mut self.phase {
            fly.scale_speed(notches);
        }
    }
}

#[derive(Clone, Copy)]
pub(super) enum PointerKind {
    Down,
    Move,
    Up,
}

/// Calls `handle` with the state for every `name` event of type `E` on `target`, for as
/// long as the page lives.
pub(super) fn on<E: JsCast + 'static>(
    target: &web_sys::EventTarget,
    name: &str,
    state: &Rc<RefCell<State>>,
    handle: impl Fn(&mut State, &E) + 'static,
) {
    let state = state.clone();
    let closure = Closure::<dyn FnMut(JsValue)>::new(move |event: JsValue| {
        if let Some(event) = event.dyn_ref::<E>() {
            handle(&mut state.borrow_mut(), event);
        }
    });
    let _ = target.add_event_listener_with_callback(name, closure.as_ref().unchecked_ref());
    closure.forget();
}

/// Keyboard on the window; pointer and wheel on the canvas.
pub(super) fn listen(state: &Rc<RefCell<State>>) {
    let (window, canvas) = {
        let s = state.borrow();
        (s.page.window.clone(), s.page.canvas.clone())
    };
    on(&window, "keydown", state, |s, e: &KeyboardEvent| s.key(e, true));
    on(&window, "keyup", state, |s, e: &KeyboardEvent| s.key(e, false));
    // Keys held when the page loses focus would stay "down" forever.
    on(&window, "blur", state, |s, _: &web_sys::Event| s.input.keys.release_all());
    for (name, kind) in [
        ("pointerdown", PointerKind::Down),
        ("pointermove", PointerKind::Move),
        ("pointerup", PointerKind::Up),
        ("pointercancel", PointerKind::Up),
    ] {
        on(&canvas, name, state, move |s, e: &PointerEvent| s.pointer(e, kind));
    }
    on(&canvas, "wheel", state, |s, e: &WheelEvent| s.wheel(e));
}
