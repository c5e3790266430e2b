#include "services/core/float_rows.h"

#include <xxhash.h>

#include <algorithm>

namespace fleetmem::core {

uint32_t RowCheck(std::span<const float> row) {
  return static_cast<uint32_t>(XXH3_64bits(row.data(), row.size_bytes()));
}

void FloatRows::Gather(std::span<const uint32_t> rows, float* values) const {
  for (const uint32_t row : rows) {
    Read(row, 1, values);
    values += width_;
  }
}

void MemoryFloatRows::Reserve(size_t rows) {
  while (blocks_.size() * kBlockRows < rows) {
    blocks_.push_back(std::make_unique<float[]>(kBlockRows * width()));
  }
}

void MemoryFloatRows::Write(size_t first, size_t count, const float* values) {
  for (size_t row = first; row < first + count;) {
    const size_t in_block =
        std::min(kBlockRows - row % kBlockRows, first + count - row);
    std::copy(values, values + in_block * width(),
              blocks_[row / kBlockRows].get() + (row % kBlockRows) * width());
    values += in_block * width();
    row += in_block;
  }
}

void MemoryFloatRows::Read(size_t first, size_t count, float* values) const {
  for (size_t row = first; row < first + count;) {
    const size_t in_block =
        std::min(kBlockRows - row % kBlockRows, first + count - row);
    const float* block =
        blocks_[row / kBlockRows].get() + (row % kBlockRows) * width();
    values = std::copy(block, block + in_block * width(), values);
    row += in_block;
  }
}

const float* MemoryFloatRows::Find(size_t row) const {
  return blocks_[row / kBlockRows].get() + (row % kBlockRows) * width();
}

size_t MemoryFloatRows::MemoryBytes() const {
  return blocks_.size() * kBlockRows * width() * sizeof(float);
}

}  // namespace fleetmem::core
