#include "clients/robot/learning/metric_head.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

namespace fleetmem::robot::gpl {
namespace {

double PlaceDistance(const core::Place& a, const core::Place& b) {
  const double dx = a.x - b.x, dy = a.y - b.y, dz = a.z - b.z;
  return std::sqrt(dx * dx + dy * dy + dz * dz);
}

// Each sample's partners: the nearest (in place) within `radius`, of
// another domain where there is one, of its own otherwise.
std::vector<std::pair<size_t, size_t>> Pairs(
    std::span<const LearnSample> samples, double radius, int max_partners) {
  std::vector<std::pair<size_t, size_t>> pairs;
  std::vector<std::pair<double, size_t>> other, same;
  for (size_t i = 0; i < samples.size(); ++i) {
    other.clear();
    same.clear();
    for (size_t j = 0; j < samples.size(); ++j) {
      if (j == i) continue;
      const double d = PlaceDistance(samples[i].place, samples[j].place);
      if (d > radius) continue;
      (samples[j].domain != samples[i].domain ? other : same).push_back({d, j});
    }
    std::vector<std::pair<double, size_t>>& pick = other.empty() ? same : other;
    const size_t n = std::min(pick.size(), size_t(std::max(0, max_partners)));
    std::partial_sort(pick.begin(), pick.begin() + n, pick.end());
    for (size_t k = 0; k < n; ++k) pairs.push_back({i, pick[k].second});
  }
  return pairs;
}

constexpr char kMagic[8] = {'F', 'M', 'H', 'E', 'A', 'D', '0', '1'};

template <typename T>
void Put(std::string& out, T value) {
  out.append(reinterpret_cast<const char*>(&value), sizeof(T));
}

void PutMatrix(std::string& out, const Eigen::MatrixXd& m) {
  Put<int64_t>(out, m.rows());
  Put<int64_t>(out, m.cols());
  out.append(reinterpret_cast<const char*>(m.data()),
             sizeof(double) * size_t(m.size()));
}

// Reads what Put/PutMatrix wrote; false once the bytes run out.
class Reader {
 public:
  explicit Reader(std::string_view bytes) : bytes_(bytes) {}
  template <typename T>
  bool Get(T* value) {
    if (bytes_.size() < sizeof(T)) return false;
    std::memcpy(value, bytes_.data(), sizeof(T));
    bytes_.remove_prefix(sizeof(T));
    return true;
  }
  bool GetMatrix(Eigen::MatrixXd* m, int64_t max_side) {
    int64_t rows = 0, cols = 0;
    if (!Get(&rows) || !Get(&cols) || rows < 0 || cols < 0 || rows > max_side ||
        cols > max_side ||
        bytes_.size() < sizeof(double) * size_t(rows * cols)) {
      return false;
    }
    m->resize(rows, cols);
    std::memcpy(m->data(), bytes_.data(), sizeof(double) * size_t(rows * cols));
    bytes_.remove_prefix(sizeof(double) * size_t(rows * cols));
    return true;
  }
  bool done() const { return bytes_.empty(); }

 private:
  std::string_view bytes_;
};

}  // namespace

std::string MetricHead::Serialize() const {
  std::string out(kMagic, sizeof(kMagic));
  Put<int32_t>(out, code_dimension_);
  Put<int32_t>(out, options_.dimension);
  Put<double>(out, options_.update_rate);
  Put<double>(out, options_.ridge);
  Put<double>(out, options_.pair_radius);
  Put<int32_t>(out, options_.max_partners);
  Put<float>(out, options_.margin);
  Put<double>(out, options_.mining.positive_radius);
  Put<double>(out, options_.mining.negative_radius);
  Put<uint8_t>(out, fitted_ ? 1 : 0);
  Put<uint8_t>(out, has_pairs_ ? 1 : 0);
  if (fitted_) {
    PutMatrix(out, mean_);
    PutMatrix(out, second_moment_);
  }
  if (has_pairs_) PutMatrix(out, difference_moment_);
  return out;
}

absl::StatusOr<MetricHead> MetricHead::Deserialize(std::string_view bytes,
                                                   int code_dimension) {
  auto lost = [](const char* what) {
    return absl::DataLossError(absl::StrCat("metric head: ", what));
  };
  if (bytes.size() < sizeof(kMagic) ||
      std::memcmp(bytes.data(), kMagic, sizeof(kMagic)) != 0) {
    return lost("not a metric head (magic)");
  }
  Reader in(bytes.substr(sizeof(kMagic)));
  int32_t dim = 0;
  MetricHeadOptions o;
  uint8_t fitted = 0, has_pairs = 0;
  if (!in.Get(&dim) || !in.Get(&o.dimension) || !in.Get(&o.update_rate) ||
      !in.Get(&o.ridge) || !in.Get(&o.pair_radius) ||
      !in.Get(&o.max_partners) || !in.Get(&o.margin) ||
      !in.Get(&o.mining.positive_radius) ||
      !in.Get(&o.mining.negative_radius) || !in.Get(&fitted) ||
      !in.Get(&has_pairs) || dim < 1 || dim > (1 << 16)) {
    return lost("truncated or malformed header");
  }
  if (code_dimension > 0 && dim != code_dimension) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "metric head: made for codes of %d values, the encoder gives %d", dim,
        code_dimension));
  }
  MetricHead head(dim, o);
  head.fitted_ = fitted != 0;
  head.has_pairs_ = has_pairs != 0;
  Eigen::MatrixXd mean;
  if (head.fitted_ &&
      (!in.GetMatrix(&mean, dim) || mean.rows() != dim || mean.cols() != 1 ||
       !in.GetMatrix(&head.second_moment_, dim) ||
       head.second_moment_.rows() != dim ||
       head.second_moment_.cols() != dim)) {
    return lost("truncated or malformed estimates");
  }
  if (head.has_pairs_ && (!in.GetMatrix(&head.difference_moment_, dim) ||
                          head.difference_moment_.rows() != dim ||
                          head.difference_moment_.cols() != dim)) {
    return lost("truncated or malformed pair estimates");
  }
  if (!in.done()) return lost("trailing bytes");
  if (head.has_pairs_ && !head.fitted_) return lost("pairs without a fit");
  if (head.fitted_) {
    head.mean_ = mean.col(0);
    head.Refit();
  }
  return head;
}

MetricHead::MetricHead(int code_dimension, MetricHeadOptions options)
    : code_dimension_(code_dimension), options_(std::move(options)) {}

int MetricHead::descriptor_dimension() const {
  return fitted_ ? int(projection_.rows()) : code_dimension_;
}

absl::Status MetricHead::CheckDimension(const std::vector<float>& code) const {
  if (code_dimension_ < 1) {
    return absl::InvalidArgumentError(
        absl::StrFormat("metric head: code dimension %d", code_dimension_));
  }
  if (int(code.size()) != code_dimension_) {
    return absl::InvalidArgumentError(
        absl::StrFormat("metric head: a code of %d values, expected %d",
                        code.size(), code_dimension_));
  }
  return absl::OkStatus();
}

Eigen::VectorXd MetricHead::Unit(const std::vector<float>& code) const {
  Eigen::VectorXd x(code.size());
  for (size_t c = 0; c < code.size(); ++c) x(c) = code[c];
  const double norm = x.norm();
  if (norm > 0) x /= norm;
  return x;
}

absl::StatusOr<MetricLearnStats> MetricHead::Learn(
    std::span<const LearnSample> samples) {
  for (const LearnSample& s : samples) {
    if (absl::Status st = CheckDimension(s.code); !st.ok()) return st;
  }
  MetricLearnStats stats;
  stats.samples = samples.size();
  if (samples.size() < 2) return stats;
  const int d = code_dimension_;
  Eigen::MatrixXd x(samples.size(), d);
  for (size_t i = 0; i < samples.size(); ++i)
    x.row(i) = Unit(samples[i].code).transpose();
  const auto pairs =
      Pairs(samples, options_.pair_radius, options_.max_partners);
  Eigen::MatrixXd diffs(pairs.size(), d);
  for (size_t p = 0; p < pairs.size(); ++p) {
    diffs.row(p) = x.row(pairs[p].first) - x.row(pairs[p].second);
    if (samples[pairs[p].first].domain != samples[pairs[p].second].domain)
      ++stats.cross_domain_pairs;
  }
  // Weighted statistics: a row scaled by sqrt(w) enters the moments with
  // weight w; a pair carries its first sample's weight. Unweighted (every
  // weight 1) the plain means.
  const bool weighted =
      std::any_of(samples.begin(), samples.end(),
                  [](const LearnSample& s) { return s.weight != 1.0; });
  double n = double(samples.size()), pair_total = double(pairs.size());
  Eigen::VectorXd mean;
  if (weighted) {
    Eigen::VectorXd w(samples.size());
    for (size_t i = 0; i < samples.size(); ++i)
      w(i) = std::max(0.0, samples[i].weight);
    n = w.sum();
    if (n <= 0)
      return absl::InvalidArgumentError(
          "metric head: every sample's weight is 0; nothing learned");
    mean = (x.transpose() * w) / n;
    x = w.cwiseSqrt().asDiagonal() * x;
    pair_total = 0;
    for (size_t p = 0; p < pairs.size(); ++p) {
      diffs.row(p) *= std::sqrt(w(pairs[p].first));
      pair_total += w(pairs[p].first);
    }
  } else {
    mean = x.colwise().mean().transpose();
  }
  const Eigen::MatrixXd second = (x.transpose() * x) / n;
  Eigen::MatrixXd difference;
  if (!pairs.empty() && pair_total > 0)
    difference = (diffs.transpose() * diffs) / pair_total;
  stats.pairs = pairs.size();
  const double eta = fitted_ ? std::clamp(options_.update_rate, 0.0, 1.0) : 1.0;
  if (!fitted_) {
    mean_ = mean;
    second_moment_ = second;
  } else {
    mean_ = (1 - eta) * mean_ + eta * mean;
    second_moment_ = (1 - eta) * second_moment_ + eta * second;
  }
  if (difference.size() > 0) {
    difference_moment_ =
        has_pairs_
            ? Eigen::MatrixXd((1 - eta) * difference_moment_ + eta * difference)
            : difference;
    has_pairs_ = true;
  }
  fitted_ = true;
  Refit();
  return stats;
}

void MetricHead::Refit() {
  const int d = code_dimension_;
  const int k = std::clamp(options_.dimension, 1, d);
  const Eigen::MatrixXd covariance = second_moment_ - mean_ * mean_.transpose();
  // Eigenvalues ascending: the principal components are the last k.
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> pca(covariance);
  const Eigen::MatrixXd basis = pca.eigenvectors().rightCols(k);  // d x k
  if (!has_pairs_) {
    projection_ = basis.transpose();
    return;
  }
  const Eigen::MatrixXd within =
      basis.transpose() * difference_moment_ * basis;  // k x k
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> white(within);
  const Eigen::VectorXd values = white.eigenvalues().cwiseMax(0.0);
  const double floor = options_.ridge * std::max(values.mean(), 1e-12);
  const Eigen::VectorXd scale = (values.array() + floor).rsqrt().matrix();  // k
  projection_ = scale.asDiagonal() * white.eigenvectors().transpose() *
                basis.transpose();  // k x d
}

absl::StatusOr<std::vector<std::vector<float>>> MetricHead::Describe(
    std::span<const std::vector<float>> codes) const {
  std::vector<std::vector<float>> out;
  out.reserve(codes.size());
  for (const std::vector<float>& code : codes) {
    if (absl::Status st = CheckDimension(code); !st.ok()) return st;
    Eigen::VectorXd y = Unit(code);
    if (fitted_) y = projection_ * (y - mean_);
    const double norm = y.norm();
    if (norm > 0) y /= norm;
    out.emplace_back(y.data(), y.data() + y.size());
  }
  return out;
}

absl::StatusOr<std::vector<float>> MetricHead::ExternalRewards(
    std::span<const LearnSample> segment,
    std::span<const LearnSample> memory) const {
  std::vector<float> rewards(segment.size(), 0.0f);
  if (segment.empty()) return rewards;
  std::vector<TripletSample> pool;
  std::vector<std::vector<float>> codes;
  for (std::span<const LearnSample> part : {segment, memory}) {
    for (const LearnSample& s : part) {
      pool.push_back({s.place, s.domain});
      codes.push_back(s.code);
    }
  }
  absl::StatusOr<std::vector<std::vector<float>>> descriptors = Describe(codes);
  if (!descriptors.ok()) return descriptors.status();
  std::vector<size_t> anchors(segment.size());
  for (size_t i = 0; i < anchors.size(); ++i) anchors[i] = i;
  for (const TripletIndex& t :
       HardestTriplets(pool, anchors, *descriptors, options_.mining)) {
    auto squared = [&](size_t a, size_t b) {
      double sum = 0;
      for (size_t c = 0; c < (*descriptors)[a].size(); ++c) {
        const double diff = (*descriptors)[a][c] - (*descriptors)[b][c];
        sum += diff * diff;
      }
      return sum;
    };
    rewards[t.anchor] =
        float(std::max(0.0, squared(t.anchor, t.positive) + options_.margin -
                                squared(t.anchor, t.negative)));
  }
  return rewards;
}

}  // namespace fleetmem::robot::gpl
