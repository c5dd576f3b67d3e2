// A Web Worker that decodes tile payloads off the page's thread, with the same wasm
// module as the player (its `decode_tile`). Messages: {id, layer (JSON), key [layer,
// lod, x, y], payload (Uint8Array, transferred), compressed} -> {id, tile (Uint8Array,
// transferred)}, {id, error} for a payload that is not a tile, or {id, unavailable}
// once the module trapped (a decoder bug): the page then decodes itself. {id, earth: true}
// asks for the built-in whole-Earth picture, answered as a tile is (its `decode_earth`).
import init, { decode_earth, decode_tile } from './terrastream_web.js';

const ready = init();
let trapped = false;
onmessage = async (event) => {
  const { id, earth, layer, key, payload, compressed } = event.data;
  await ready;
  if (trapped) {
    postMessage({ id, unavailable: true });
    return;
  }
  try {
    const tile = earth ? decode_earth() : decode_tile(layer, Uint32Array.from(key), payload, compressed);
    postMessage({ id, tile }, [tile.buffer]);
  } catch (error) {
    // A trap leaves the module unusable: this tile is undecodable, later ones go back.
    trapped = error instanceof WebAssembly.RuntimeError;
    postMessage({ id, error: String(error) });
  }
};
