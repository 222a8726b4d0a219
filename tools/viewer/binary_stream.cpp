#include "kestrel/viewer/binary_stream.hpp"

namespace kestrel::viewer {

BinaryStream::BinaryStream(std::size_t slot_bytes) : buffers_(kSlots), sizes_(kSlots, 0) {
  for (uint32_t i = 0; i < kSlots; ++i) {
    buffers_[i].assign(slot_bytes, 0);
    (void)free_.try_push(i);
  }
}

uint8_t* BinaryStream::acquire(std::size_t* capacity) noexcept {
  const uint32_t* i = free_.front();
  if (i == nullptr) return nullptr;
  *capacity = buffers_[*i].size();
  return buffers_[*i].data();
}

void BinaryStream::publish(std::size_t bytes) noexcept {
  const uint32_t* i = free_.front();
  if (i == nullptr) return;  // publish without acquire: nothing to hand over
  const uint32_t slot = *i;
  free_.pop();
  sizes_[slot] = bytes;
  (void)filled_.try_push(slot);  // never full: kSlots slots in all
  published_.fetch_add(1, std::memory_order_relaxed);
}

bool BinaryStream::take(const uint8_t** data, std::size_t* size, uint32_t* slot) noexcept {
  const uint32_t* i = filled_.front();
  if (i == nullptr) return false;
  *slot = *i;
  filled_.pop();
  *data = buffers_[*slot].data();
  *size = sizes_[*slot];
  return true;
}

}  // namespace kestrel::viewer
