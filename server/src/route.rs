//! The server's routes, once: the router mounts a handler on each template, the metrics
//! count requests by route, and the lean HTTP/1.1 path classifies a request path with the
//! same [`Route::of`] the router's matching follows.

use axum::http::HeaderName;
use axum::http::header::{
    ACCEPT_ENCODING, IF_MATCH, IF_MODIFIED_SINCE, IF_NONE_MATCH, IF_RANGE, IF_UNMODIFIED_SINCE, RANGE,
};

/// The request headers the archive and tile handlers read: the lean path keeps only these
/// (others are checked, not copied), and a browser's preflight is told it may send them.
pub(crate) const READ_HEADERS: [HeaderName; 7] =
    [RANGE, IF_RANGE, IF_MATCH, IF_NONE_MATCH, IF_MODIFIED_SINCE, IF_UNMODIFIED_SINCE, ACCEPT_ENCODING];

/// A route of the application.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Route {
    /// `/`: the archive list.
    Index,
    /// `/healthz`.
    Health,
    /// `/metrics`: Prometheus text.
    Metrics,
    /// `/auth`: the access rules' answer for another URI (a proxy's `auth_request`).
    Auth,
    /// `/{file}`: an archive's bytes (Range requests).
    Archive,
    /// `/{name}/metadata`.
    Metadata,
    /// `/{name}/{layer}/{lod}/{x}/{y}`: one tile.
    Tile,
    /// `/view/{name}`: the webplayer on an archive.
    View,
    /// `/{name}/tiles.json`: the elevation's TileJSON.
    TileJson,
    /// `/{name}/{layer}/tiles.json`: a layer's TileJSON.
    LayerTileJson,
    /// `/{name}/xyz/{layer}/{z}/{x}/{y}.{ext}`: a Web Mercator tile.
    WebTile,
    /// `/v1/{name}`: the elevation API.
    Elevation,
    /// `/{name}/layer.json`: the quantized-mesh terrain's layer.
    LayerJson,
    /// `/{name}/{z}/{x}/{y}.terrain`: a quantized-mesh tile.
    TerrainTile,
    /// `/{name}/contours/{z}/{x}/{y}.pbf`: a contour vector tile.
    Contours,
    /// `/fonts/{fontstack}/{range}.pbf`: glyphs for map labels.
    Fonts,
    /// Anything else (answered 404; counted under "other").
    Other,
}

impl Route {
    /// Every route, in the order the metrics list them.
    pub const ALL: [Self; 17] = [
        Self::Index,
        Self::Health,
        Self::Metrics,
        Self::Auth,
        Self::Archive,
        Self::Metadata,
        Self::Tile,
        Self::View,
        Self::TileJson,
        Self::LayerTileJson,
        Self::WebTile,
        Self::Elevation,
        Self::LayerJson,
        Self::TerrainTile,
        Self::Contours,
        Self::Fonts,
        Self::Other,
    ];

    /// The router's path template (axum's syntax), which also labels the route in the
    /// metrics; "other" for [`Route::Other`].
    pub const fn template(self) -> &'static str {
        match self {
            Self::Index => "/",
            Self::Health => "/healthz",
            Self::Metrics => "/metrics",
            Self::Auth => "/auth",
            Self::Archive => "/{file}",
            Self::Metadata => "/{name}/metadata",
            Self::Tile => "/{name}/{layer}/{lod}/{x}/{y}",
            Self::View => "/view/{name}",
            Self::TileJson => "/{name}/tiles.json",
            Self::LayerTileJson => "/{name}/{layer}/tiles.json",
            Self::WebTile => "/{name}/xyz/{layer}/{z}/{x}/{y}",
            Self::Elevation => "/v1/{name}",
            Self::LayerJson => "/{name}/layer.json",
            Self::TerrainTile => "/{name}/{z}/{x}/{y}",
            Self::Contours => "/{name}/contours/{z}/{x}/{y}",
            Self::Fonts => "/fonts/{fontstack}/{range}",
            Self::Other => "other",
        }
    }

    /// Position in [`Route::ALL`].
    pub const fn index(self) -> usize {
        self as usize
    }

    /// The route whose template is `template` ([`Route::Other`] for any other text).
    pub fn from_template(template: &str) -> Self {
        Self::ALL.into_iter().find(|r| r.template() == template).unwrap_or(Self::Other)
    }

    /// The route that serves a request path, as the router matches it (static segments
    /// before parameters, no empty segment), without running the router.
    pub fn of(path: &str) -> Self {
        let mut segments = path.strip_prefix('/').unwrap_or(path).split('/');
        let first = segments.next().unwrap_or("");
        let rest: [Option<&str>; 6] = std::array::from_fn(|_| segments.next());
        match (first, rest) {
            ("", [None, ..]) => Self::Index,
            ("healthz", [None, ..]) => Self::Health,
            ("metrics", [None, ..]) => Self::Metrics,
            ("auth", [None, ..]) => Self::Auth,
            (f, [None, ..]) if !f.is_empty() => Self::Archive,
            ("view", [Some(n), None, ..]) if !n.is_empty() => Self::View,
            ("v1", [Some(n), None, ..]) if !n.is_empty() => Self::Elevation,
            ("fonts", [Some(s), Some(r), None, ..]) if !s.is_empty() && !r.is_empty() => Self::Fonts,
            (f, [Some("metadata"), None, ..]) if !f.is_empty() => Self::Metadata,
            (f, [Some("tiles.json"), None, ..]) if !f.is_empty() => Self::TileJson,
            (f, [Some("layer.json"), None, ..]) if !f.is_empty() => Self::LayerJson,
            (f, [Some(l), Some("tiles.json"), None, ..]) if !f.is_empty() && !l.is_empty() => Self::LayerTileJson,
            (f, [Some("xyz"), Some(l), Some(z), Some(x), Some(y), None]) if ![f, l, z, x, y].contains(&"") => {
                Self::WebTile
            }
            (f, [Some("contours"), Some(z), Some(x), Some(y), None, ..]) if ![f, z, x, y].contains(&"") => {
                Self::Contours
            }
            (f, [Some(a), Some(b), Some(c), Some(d), None, ..]) if ![f, a, b, c, d].contains(&"") => Self::Tile,
            (f, [Some(z), Some(x), Some(y), None, ..]) if ![f, z, x, y].contains(&"") => Self::TerrainTile,
            _ => Self::Other,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_are_classified_as_the_router_matches_them() {
        let cases = [
            ("/", "/"),
            ("/healthz", "/healthz"),
            ("/metrics", "/metrics"),
            ("/auth", "/auth"),
            ("/a.tspack", "/{file}"),
            ("/view/a", "/view/{name}"),
            ("/view/metadata", "/view/{name}"),
            ("/a/metadata", "/{name}/metadata"),
            ("/a/texture/0/1/2", "/{name}/{layer}/{lod}/{x}/{y}"),
            ("/a/b", "other"),
            ("/a/b/c", "other"),
            ("/a/texture/0/1/2/3", "other"),
            ("/a/tiles.json", "/{name}/tiles.json"),
            ("/a/elevation/tiles.json", "/{name}/{layer}/tiles.json"),
            ("/a/xyz/elevation/12/655/1582.webp", "/{name}/xyz/{layer}/{z}/{x}/{y}"),
            ("/a/xyz/elevation/12/655/1582.webp/x", "other"),
            ("/a/layer.json", "/{name}/layer.json"),
            ("/a/12/655/1582.terrain", "/{name}/{z}/{x}/{y}"),
            ("/a/contours/12/655/1582.pbf", "/{name}/contours/{z}/{x}/{y}"),
            ("/v1/a", "/v1/{name}"),
            ("/v1/", "other"),
            ("/a//0/1/2", "other"),
            ("/view/", "other"),
        ];
        for (path, route) in cases {
            assert_eq!(Route::of(path).template(), route, "{path}");
        }
        // The paths the clients build (terrastream_format::protocol) land on their routes.
        use terrastream_format::{TileKey, protocol};
        assert_eq!(Route::of(&format!("/alps/{}", protocol::METADATA_PATH)), Route::Metadata);
        let tile = protocol::tile_path(TileKey::new(1, 2, 3, 4).unwrap());
        assert_eq!(Route::of(&format!("/alps/{tile}")), Route::Tile);
        for (i, route) in Route::ALL.into_iter().enumerate() {
            assert_eq!(route.index(), i);
            assert_eq!(Route::from_template(route.template()), route);
        }
    }
}
