//! Decoding off the page's thread: a pool of Web Workers (`decoder.js`, a module worker
//! that loads this same wasm module) decodes tile payloads and hands back flat decoded
//! tiles ([`DecodedTile::to_wire`]). A worker that fails to start, dies, or whose module
//! trapped makes its tiles decode on the page's thread instead
//! ([`DecodeFailure::Unavailable`]).

use std::cell::{Cell, RefCell};
use std::collections::HashMap;
use std::rc::Rc;

use bytes::Bytes;
use futures_channel::oneshot;
use js_sys::{Array, Object, Reflect, Uint8Array};
use terrastream_client::render::EarthPicture;
use terrastream_client::{DecodeFailure, DecodedTile, Decoder};
use terrastream_format::{Layer, TileKey};
use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;

/// What a worker answers for one request: the decoded tile's bytes, or why not.
type Answer = Result<Vec<u8>, DecodeFailure>;

/// The workers and the requests waiting on them.
pub struct Pool {
    workers: Vec<web_sys::Worker>,
    next: Cell<usize>,
    next_id: Cell<u32>,
    waiting: Rc<RefCell<HashMap<u32, oneshot::Sender<Answer>>>>,
    broken: Rc<Cell<bool>>,
    decoded: Rc<Cell<u64>>,
    /// Whether a worker's whole-Earth picture was handed to the renderer.
    earth: Rc<Cell<bool>>,
    _handlers: Vec<Closure<dyn FnMut(web_sys::MessageEvent)>>,
    _errors: Vec<Closure<dyn FnMut(web_sys::Event)>>,
}

impl Pool {
    /// Starts `count` workers from `decoder.js` beside the page.
    ///
    /// # Errors
    /// The browser's message when a worker cannot be made.
    pub fn start(count: usize) -> Result<Rc<Self>, JsValue> {
        let document = web_sys::window().and_then(|w| w.document()).ok_or("no document")?;
        let base = document.base_uri()?.unwrap_or_default();
        let url = web_sys::Url::new_with_base("decoder.js", &base)?.href();
        let options = web_sys::WorkerOptions::new();
        options.set_type(web_sys::WorkerType::Module);
        let waiting: Rc<RefCell<HashMap<u32, oneshot::Sender<Answer>>>> = Rc::default();
        let broken = Rc::new(Cell::new(false));
        let (mut workers, mut handlers, mut errors) = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..count.max(1) {
            let worker = web_sys::Worker::new_with_options(&url, &options)?;
            let pending = waiting.clone();
            let on_message = Closure::<dyn FnMut(_)>::new(move |event: web_sys::MessageEvent| {
                let data = event.data();
                let id = Reflect::get(&data, &"id".into()).ok().and_then(|v| v.as_f64());
                #[expect(clippy::cast_possible_truncation, clippy::cast_sign_loss, reason = "ids are u32")]
                let Some(sender) = id.and_then(|id| pending.borrow_mut().remove(&(id as u32))) else { return };
                let field = |name: &str| Reflect::get(&data, &name.into()).ok().filter(|v| !v.is_undefined());
                let answer = match (field("tile"), field("unavailable")) {
                    (Some(tile), _) => Ok(Uint8Array::new(&tile).to_vec()),
                    (None, Some(_)) => Err(DecodeFailure::Unavailable),
                    (None, None) => Err(DecodeFailure::Undecodable(
                        Reflect::get(&data, &"error".into()).ok().and_then(|e| e.as_string()).unwrap_or_default(),
                    )),
                };
                let _ = sender.send(answer);
            });
            worker.set_onmessage(Some(on_message.as_ref().unchecked_ref()));
            // A worker that cannot load (or dies): everything waiting, and what comes
            // after, decodes on the page's thread.
            let (pending, failed) = (waiting.clone(), broken.clone());
            let on_error = Closure::<dyn FnMut(_)>::new(move |_: web_sys::Event| {
                tracing::warn!("a decoding worker failed: decoding on the page's thread");
                failed.set(true);
                for (_, sender) in pending.borrow_mut().drain() {
                    let _ = sender.send(Err(DecodeFailure::Unavailable));
                }
            });
            worker.set_onerror(Some(on_error.as_ref().unchecked_ref()));
            workers.push(worker);
            handlers.push(on_message);
            errors.push(on_error);
        }
        Ok(Rc::new(Self {
            workers,
            next: Cell::new(0),
            next_id: Cell::new(0),
            waiting,
            broken,
            decoded: Rc::default(),
            earth: Rc::default(),
            _handlers: handlers,
            _errors: errors,
        }))
    }

    /// Workers in the pool.
    pub fn len(&self) -> usize {
        self.workers.len()
    }

    /// Tiles the workers decoded.
    pub fn decoded(&self) -> u64 {
        self.decoded.get()
    }

    /// Whether a worker decoded the whole-Earth picture that frames draw.
    pub fn decoded_earth(&self) -> bool {
        self.earth.get()
    }

    /// The pool as the streamer's decoder.
    pub fn decoder(self: &Rc<Self>) -> Decoder {
        let pool = self.clone();
        // A layer's JSON, made once per layer.
        let layers: Rc<RefCell<HashMap<String, String>>> = Rc::default();
        Rc::new(move |layer: &Layer, key: TileKey, payload: Bytes, compressed: bool| {
            let json = layers
                .borrow_mut()
                .entry(layer.name.clone())
                .or_insert_with(|| serde_json::to_string(layer).unwrap_or_default())
                .clone();
            let answer = pool.send(&json, key, &payload, compressed);
            let decoded = pool.decoded.clone();
            Box::pin(async move {
                let bytes = answer.await.unwrap_or(Err(DecodeFailure::Unavailable))?;
                let tile = DecodedTile::from_wire(&bytes).map_err(|e| DecodeFailure::Undecodable(e.to_string()))?;
                decoded.set(decoded.get() + 1);
                Ok(tile)
            })
        })
    }

    /// Has the next worker decode the whole-Earth picture, which the renderer takes once it
    /// comes; frames draw the plain ground beyond the data until then. Where the worker
    /// cannot, the page's first frame with a sky decodes it itself.
    pub fn decode_earth(&self) {
        let (sender, receiver) = oneshot::channel();
        let id = self.next_id.get().wrapping_add(1);
        self.next_id.set(id);
        let message = Object::new();
        let built = Reflect::set(&message, &"id".into(), &id.into()).is_ok()
            && Reflect::set(&message, &"earth".into(), &true.into()).is_ok();
        if self.broken.get() || self.workers.is_empty() || !built {
            return;
        }
        let worker = &self.workers[self.next.get() % self.workers.len()];
        self.next.set(self.next.get().wrapping_add(1));
        self.waiting.borrow_mut().insert(id, sender);
        terrastream_client::render::decoding_elsewhere();
        if worker.post_message(&message).is_err() {
            self.waiting.borrow_mut().remove(&id);
            terrastream_client::render::decoded_elsewhere(None);
            return;
        }
        let decoded = self.earth.clone();
        wasm_bindgen_futures::spawn_local(async move {
            let picture = match receiver.await {
                Ok(Ok(bytes)) => EarthPicture::from_wire(bytes),
                Ok(Err(e)) => {
                    tracing::warn!(
                        "the Earth picture was not decoded in a worker ({e:?}): decoding on the page's thread"
                    );
                    None
                }
                Err(_) => None,
            };
            decoded.set(picture.is_some());
            terrastream_client::render::decoded_elsewhere(picture);
        });
    }

    /// Posts one payload to the next worker (its bytes transferred, not copied twice).
    fn send(&self, layer: &str, key: TileKey, payload: &[u8], compressed: bool) -> oneshot::Receiver<Answer> {
        let (sender, receiver) = oneshot::channel();
        if self.broken.get() || self.workers.is_empty() {
            let _ = sender.send(Err(DecodeFailure::Unavailable));
            return receiver;
        }
        let id = self.next_id.get().wrapping_add(1);
        self.next_id.set(id);
        let bytes = Uint8Array::from(payload);
        let message = Object::new();
        let key_array =
            Array::of4(&key.layer().into(), &key.lod().into(), &JsValue::from(key.x()), &JsValue::from(key.y()));
        let set = |name: &str, value: &JsValue| Reflect::set(&message, &name.into(), value).is_ok();
        let built = set("id", &id.into())
            && set("layer", &layer.into())
            && set("key", &key_array)
            && set("payload", &bytes)
            && set("compressed", &compressed.into());
        let worker = &self.workers[self.next.get() % self.workers.len()];
        self.next.set(self.next.get().wrapping_add(1));
        self.waiting.borrow_mut().insert(id, sender);
        let transfer = Array::of1(&bytes.buffer());
        if (!built || worker.post_message_with_transfer(&message, &transfer).is_err())
            && let Some(sender) = self.waiting.borrow_mut().remove(&id)
        {
            let _ = sender.send(Err(DecodeFailure::Unavailable));
        }
        receiver
    }
}

/// Decodes the whole-Earth picture built into the module (what `decoder.js` calls in a
/// worker for [`Pool::decode_earth`]): [`EarthPicture::to_wire`]'s bytes.
///
/// # Errors
/// When the built-in picture does not decode (a test rules that out).
#[wasm_bindgen]
pub fn decode_earth() -> Result<Vec<u8>, JsValue> {
    std::panic::catch_unwind(EarthPicture::decode)
        .ok()
        .flatten()
        .map(|picture| picture.to_wire())
        .ok_or_else(|| JsValue::from_str("the built-in Earth picture does not decode"))
}

/// Decodes one payload (what `decoder.js` calls in a worker): the decoded tile as flat
/// bytes ([`DecodedTile::to_wire`]).
///
/// # Errors
/// Why the payload is not a tile of its layer.
#[wasm_bindgen]
pub fn decode_tile(layer: &str, key: &[u32], payload: &[u8], compressed: bool) -> Result<Vec<u8>, JsValue> {
    let layer: Layer = serde_json::from_str(layer).map_err(|e| JsValue::from_str(&format!("layer: {e}")))?;
    let field = |i: usize| key.get(i).copied().unwrap_or(0);
    let (index, lod) = (u8::try_from(field(0)).unwrap_or(u8::MAX), u8::try_from(field(1)).unwrap_or(u8::MAX));
    let key = TileKey::new(index, lod, field(2), field(3)).map_err(|e| JsValue::from_str(&e.to_string()))?;
    // A decoder that panics (a bug: they are fuzzed) costs that tile, not the worker.
    // The page draws every tile it asks for: an elevation tile's shade texels are made
    // here too, off the page's thread.
    let decoded = std::panic::catch_unwind(|| {
        terrastream_client::decode(&layer, key, payload, compressed).map(|mut tile| {
            tile.shade(&layer);
            tile
        })
    })
    .map_err(|_| JsValue::from_str(&format!("tile {key} of layer {:?}: the decoder failed", layer.name)))?;
    decoded.map(|tile| tile.to_wire()).map_err(|e| JsValue::from_str(&e.to_string()))
}
