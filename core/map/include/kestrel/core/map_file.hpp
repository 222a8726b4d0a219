// The map as bytes (`kestrel replay|run --map-out / --map-in`, docs/map.md):
// core turns a Map into a sealed byte image and back (bytes.hpp: magic KMAP,
// format version, payload length, CRC-32) and does no I/O; tools read and
// write the files. The payload records the vocabulary the BoW vectors came
// from (its checksum) and the camera the features were seen with, so a map
// from another vocabulary or another camera is refused by name instead of
// being matched against nonsense.
//
// decode_map is the one entry point for untrusted bytes (a fuzz target is a
// call of it): it never reads past the end, checks every count and index
// before it touches the Map, and returns what is wrong instead of throwing.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "kestrel/core/local_mapper.hpp"
#include "kestrel/core/map.hpp"

namespace kestrel::core {

constexpr char kMapMagic[4] = {'K', 'M', 'A', 'P'};
constexpr uint32_t kMapVersion = 1;

// Every keyframe with its features and the points they observe, in keyframe
// id order. Loop edges and statistics are not kept: a loaded map is a set of
// places to localise in, and its own pose graph is already solved.
std::vector<uint8_t> encode_map(const Map& map, const MapCamera& cam);

struct MapFileInfo {
  uint32_t vocabulary_checksum = 0;  // 0: saved without a vocabulary
  int keyframes = 0, points = 0;
};

// Fills `map` (which must be empty) from bytes made by encode_map: the
// keyframes come in as session 1 (MapKeyframe::session), the points get fresh
// landmark ids (2^31 up; the tracker of this flight never gave them).
// Returns "" or what is wrong (damaged, truncated, foreign, another version,
// another vocabulary or camera, larger than the map's capacity); on error the
// map may hold part of the file and should be discarded.
std::string decode_map(const uint8_t* data, size_t n, const MapCamera& cam, Map* map,
                       MapFileInfo* info = nullptr);

}  // namespace kestrel::core
