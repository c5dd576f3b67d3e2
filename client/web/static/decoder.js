// A Web Worker that decodes tile payloads off the page's thread, with the same wasm
// module as the player (its `decode_tile`). Messages: {id, layer (JSON), key [layer,
// lod, x, y], payload (Uint8Array, transferred), compressed} -> {id, tile (Uint8Array,
// transferred)} or {id, error}.
import init, { decode_tile } from './terrastream_web.js';

const ready = init();
onmessage = async (event) => {
  const { id, layer, key, payload, compressed } = event.data;
  await ready;
  try {
    const tile = decode_tile(layer, Uint32Array.from(key), payload, compressed);
    postMessage({ id, tile }, [tile.buffer]);
  } catch (error) {
    postMessage({ id, error: String(error) });
  }
};
