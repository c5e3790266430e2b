#include "services/auth/authenticator.h"

#include <sodium.h>

#include <algorithm>
#include <utility>

#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "services/auth/credentials.pb.h"
#include "services/auth/secret.h"
#include "services/common/text_format.h"
#include "services/core/validation.h"

namespace fleetmem::auth {
namespace {

// Most distinct wrong tokens whose check is cached; that cache is emptied
// when full (a flood of wrong tokens never costs unbounded memory, and never
// evicts the valid tokens' checks).
constexpr size_t kMaxCachedTokens = 4096;

absl::Status Bad(int index, absl::string_view name, absl::string_view why) {
  return absl::InvalidArgumentError(
      absl::StrCat("principal ", index + 1, " (\"", name, "\"): ", why));
}

absl::StatusOr<CredentialEntry> ToEntry(int index, const file::Principal& in) {
  CredentialEntry out;
  if (absl::Status valid = core::ValidateId("name", in.name()); !valid.ok()) {
    return Bad(index, in.name(), valid.message());
  }
  out.principal.name = in.name();
  switch (in.role()) {
    case file::ROBOT:
      out.principal.role = Role::kRobot;
      break;
    case file::READER:
      out.principal.role = Role::kReader;
      break;
    case file::ADMIN:
      out.principal.role = Role::kAdmin;
      break;
    default:
      return Bad(index, in.name(), "role: required (ROBOT, READER or ADMIN)");
  }
  if (out.principal.role == Role::kRobot) {
    out.principal.robot_id = in.robot_id().empty() ? in.name() : in.robot_id();
    if (absl::Status valid =
            core::ValidateId("robot_id", out.principal.robot_id);
        !valid.ok()) {
      return Bad(index, in.name(), valid.message());
    }
  } else if (!in.robot_id().empty()) {
    return Bad(index, in.name(), "robot_id: only a ROBOT has one");
  }
  for (const std::string& fleet : in.fleets()) {
    if (fleet == "*") {
      out.principal.fleets.push_back(fleet);
      continue;
    }
    if (absl::Status valid = core::ValidateId("fleets", fleet); !valid.ok()) {
      return Bad(index, in.name(), valid.message());
    }
    out.principal.fleets.push_back(fleet);
  }
  if (out.principal.role != Role::kAdmin && out.principal.fleets.empty()) {
    return Bad(index, in.name(),
               "fleets: a robot or reader needs at least one (\"*\" for all)");
  }
  if (in.secret_hash().empty() && in.certificate_common_name().empty()) {
    return Bad(index, in.name(),
               "needs secret_hash (token) or certificate_common_name (mutual "
               "TLS)");
  }
  if (!in.secret_hash().empty()) {
    if (absl::Status valid = CheckSecretHash(in.secret_hash()); !valid.ok()) {
      return Bad(index, in.name(), valid.message());
    }
    out.secret_hash = in.secret_hash();
  }
  if (in.certificate_common_name().size() > 256) {
    return Bad(index, in.name(),
               "certificate_common_name: longer than 256 characters");
  }
  out.certificate_common_name = in.certificate_common_name();
  return out;
}

}  // namespace

namespace {

bool SharesAFleet(const Principal& a, const Principal& b) {
  for (const std::string& fleet : a.fleets) {
    if (fleet == "*") return true;
    for (const std::string& other : b.fleets) {
      if (other == "*" || other == fleet) return true;
    }
  }
  return false;
}

}  // namespace

absl::StatusOr<std::vector<CredentialEntry>> ParseCredentials(
    absl::string_view text) {
  file::CredentialsFile parsed;
  if (absl::Status syntax =
          ParseTextFormat(std::string_view(text.data(), text.size()), &parsed);
      !syntax.ok()) {
    return syntax;
  }
  std::vector<CredentialEntry> entries;
  absl::flat_hash_set<std::string> names;
  absl::flat_hash_set<std::string> common_names;
  for (int i = 0; i < parsed.principal_size(); ++i) {
    absl::StatusOr<CredentialEntry> entry = ToEntry(i, parsed.principal(i));
    if (!entry.ok()) return entry.status();
    if (!names.insert(entry->principal.name).second) {
      return Bad(i, entry->principal.name,
                 "name: used by an earlier principal");
    }
    if (!entry->certificate_common_name.empty() &&
        !common_names.insert(entry->certificate_common_name).second) {
      return Bad(i, entry->principal.name,
                 "certificate_common_name: used by an earlier principal");
    }
    // Two robots acting as one robot id in a fleet would share its sequence
    // numbers: the first to upload a seq takes it, the other's come back as
    // duplicates.
    if (entry->principal.role == Role::kRobot) {
      for (const CredentialEntry& earlier : entries) {
        if (earlier.principal.role == Role::kRobot &&
            earlier.principal.robot_id == entry->principal.robot_id &&
            SharesAFleet(earlier.principal, entry->principal)) {
          return Bad(
              i, entry->principal.name,
              absl::StrCat("robot id \"", entry->principal.robot_id,
                           "\" is already principal \"", earlier.principal.name,
                           "\"'s in a fleet they share; a robot id "
                           "belongs to one principal"));
        }
      }
    }
    entries.push_back(std::move(*entry));
  }
  return entries;
}

std::string TokenFromAuthorization(absl::string_view value) {
  constexpr absl::string_view kBearer = "Bearer ";
  return std::string(
      absl::StartsWith(value, kBearer) ? value.substr(kBearer.size()) : value);
}

std::string MakeToken(absl::string_view name, absl::string_view secret) {
  return absl::StrCat(name, ":", secret);
}

struct Authenticator::Set {
  std::vector<CredentialEntry> entries;
  absl::flat_hash_map<std::string, size_t> by_name;
  absl::flat_hash_map<std::string, size_t> by_common_name;
  mutable absl::Mutex mu;
  // Keyed BLAKE2b of a token -> index into `entries`: at most one per entry.
  mutable absl::flat_hash_map<std::string, size_t> valid ABSL_GUARDED_BY(mu);
  // Keyed BLAKE2b of tokens found wrong; emptied when full.
  mutable absl::flat_hash_set<std::string> wrong ABSL_GUARDED_BY(mu);

  explicit Set(std::vector<CredentialEntry> all) : entries(std::move(all)) {
    for (size_t i = 0; i < entries.size(); ++i) {
      by_name.emplace(entries[i].principal.name, i);
      if (!entries[i].certificate_common_name.empty()) {
        by_common_name.emplace(entries[i].certificate_common_name, i);
      }
    }
  }
};

namespace {

bool SamePrincipal(const CredentialEntry& a, const CredentialEntry& b) {
  return a.secret_hash == b.secret_hash &&
         a.principal.name == b.principal.name &&
         a.principal.role == b.principal.role &&
         a.principal.robot_id == b.principal.robot_id &&
         a.principal.fleets == b.principal.fleets;
}

}  // namespace

Authenticator::Authenticator(std::vector<CredentialEntry> entries,
                             AuthenticatorOptions options)
    : options_(std::move(options)),
      set_(std::make_shared<const Set>(std::move(entries))) {
  static_assert(sizeof digest_key_ == crypto_generichash_KEYBYTES);
  if (sodium_init() >= 0) {
    randombytes_buf(digest_key_, sizeof digest_key_);
  } else {
    sodium_memzero(digest_key_, sizeof digest_key_);
  }
}

void Authenticator::Replace(std::vector<CredentialEntry> entries) {
  auto set = std::make_shared<Set>(std::move(entries));
  const std::shared_ptr<const Set> old = Current();
  {
    absl::MutexLock old_lock(&old->mu);
    absl::MutexLock new_lock(&set->mu);
    for (const auto& [digest, index] : old->valid) {
      const CredentialEntry& was = old->entries[index];
      auto now = set->by_name.find(was.principal.name);
      if (now != set->by_name.end() &&
          SamePrincipal(was, set->entries[now->second])) {
        set->valid.emplace(digest, now->second);
      }
    }
  }
  absl::MutexLock lock(&mu_);
  set_ = std::move(set);
}

std::shared_ptr<const Authenticator::Set> Authenticator::Current() const {
  absl::MutexLock lock(&mu_);
  return set_;
}

size_t Authenticator::size() const { return Current()->entries.size(); }

namespace {

// Connections and addresses remembered for throttling; beyond, the ones not
// seen for a minute are forgotten.
constexpr size_t kMaxTrackedPeers = 16384;

// "ipv4:127.0.0.1:50212" -> "ipv4:127.0.0.1"; "[::1]:80" -> "[::1]".
std::string AddressOf(const std::string& peer) {
  const size_t colon = peer.rfind(':');
  return colon == std::string::npos ? peer : peer.substr(0, colon);
}

}  // namespace

Authenticator::Check Authenticator::TakeCheck(const std::string& peer) const {
  const absl::Time now = options_.now();
  auto refill = [now](Bucket& bucket, double rate, double burst) {
    if (bucket.refilled == absl::InfinitePast()) {
      bucket.tokens = burst;
    } else {
      bucket.tokens = std::min(
          burst,
          bucket.tokens + rate * absl::ToDoubleSeconds(now - bucket.refilled));
    }
    bucket.refilled = now;
  };
  absl::MutexLock lock(&budget_mu_);
  if (connections_.size() >= kMaxTrackedPeers) {
    absl::erase_if(connections_, [now](const auto& entry) {
      return now - entry.second.seen > absl::Minutes(1);
    });
  }
  if (clean_by_address_.size() >= kMaxTrackedPeers) {
    absl::erase_if(clean_by_address_, [now](const auto& entry) {
      return now - entry.second.refilled > absl::Minutes(1);
    });
  }
  Connection& connection = connections_[peer];
  connection.seen = now;
  refill(connection.bucket, options_.checks_per_second_per_connection,
         options_.check_burst_per_connection);
  Bucket& shared =
      connection.suspect ? suspects_ : clean_by_address_[AddressOf(peer)];
  if (connection.suspect) {
    refill(shared, options_.checks_per_second, options_.check_burst);
  } else {
    refill(shared, options_.clean_checks_per_second_per_address,
           options_.clean_check_burst_per_address);
  }
  if (connection.bucket.tokens < 1.0 || shared.tokens < 1.0) {
    return Check::kRefused;
  }
  connection.bucket.tokens -= 1.0;
  shared.tokens -= 1.0;
  return connection.suspect ? Check::kSuspect : Check::kClean;
}

void Authenticator::MarkSuspect(const std::string& peer) const {
  absl::MutexLock lock(&budget_mu_);
  if (auto it = connections_.find(peer); it != connections_.end()) {
    it->second.suspect = true;
  }
}

absl::StatusOr<Principal> Authenticator::CheckToken(
    const std::shared_ptr<const Set>& set, const std::string& token,
    const std::string& peer) const {
  const absl::Status wrong = absl::UnauthenticatedError(
      "unknown or wrong token (expected \"authorization: Bearer NAME:SECRET\" "
      "for a principal of the server's credentials file)");
  unsigned char out[crypto_generichash_BYTES];
  crypto_generichash(out, sizeof out,
                     reinterpret_cast<const unsigned char*>(token.data()),
                     token.size(), digest_key_, sizeof digest_key_);
  const std::string digest(reinterpret_cast<const char*>(out), sizeof out);
  {
    absl::MutexLock lock(&set->mu);
    if (auto it = set->valid.find(digest); it != set->valid.end()) {
      return set->entries[it->second].principal;
    }
    if (set->wrong.contains(digest)) return wrong;
  }
  const size_t colon = token.rfind(':');
  auto named = colon == std::string::npos
                   ? set->by_name.end()
                   : set->by_name.find(token.substr(0, colon));
  bool found = false;
  if (named != set->by_name.end() &&
      !set->entries[named->second].secret_hash.empty()) {
    // The one costly case: a known name with a secret not seen before.
    const Check check = TakeCheck(peer);
    // A connection that has presented a wrong token does not queue for the
    // check (its call would hold a worker thread while it waits): it is
    // checked only when no other check runs.
    if (check == Check::kRefused ||
        (check == Check::kSuspect && !check_mu_.TryLock())) {
      return absl::UnavailableError(absl::StrCat(
          "the token of \"", named->first,
          "\" was not checked: this connection presents more new tokens than "
          "the server checks (",
          options_.checks_per_second_per_connection,
          " a second for a connection, fewer once it has presented a wrong "
          "one); retry later"));
    }
    if (check == Check::kClean) check_mu_.Lock();
    found = VerifySecret(set->entries[named->second].secret_hash,
                         token.substr(colon + 1));
    check_mu_.Unlock();
    if (!found) MarkSuspect(peer);
  }
  absl::MutexLock lock(&set->mu);
  if (found) {
    set->valid[digest] = named->second;
    return set->entries[named->second].principal;
  }
  if (set->wrong.size() >= kMaxCachedTokens) set->wrong.clear();
  set->wrong.insert(digest);
  return wrong;
}

absl::StatusOr<Principal> Authenticator::Authenticate(
    const PresentedCredentials& presented) const {
  const std::shared_ptr<const Set> set = Current();
  if (presented.token.has_value()) {
    return CheckToken(set, *presented.token, presented.peer);
  }
  if (presented.certificate_common_name.has_value()) {
    auto it = set->by_common_name.find(*presented.certificate_common_name);
    if (it == set->by_common_name.end()) {
      return absl::UnauthenticatedError(absl::StrCat(
          "client certificate \"", *presented.certificate_common_name,
          "\" names no principal of the server's credentials file"));
    }
    return set->entries[it->second].principal;
  }
  return absl::UnauthenticatedError(
      "no credentials: send \"authorization: Bearer NAME:SECRET\" or a client "
      "certificate");
}

}  // namespace fleetmem::auth
