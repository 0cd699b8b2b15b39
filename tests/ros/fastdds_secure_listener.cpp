// A Fast DDS 2.9 (Debian's libfastrtps) subscriber of /fall_guard/forecast
// with DDS Security from one SROS2 enclave directory, on 127.0.0.1 only.
// Build (Debian 12: apt install libfastrtps-dev g++):
//   g++ -std=c++17 -O1 tests/ros/fastdds_secure_listener.cpp -o out/fastdds_secure_listener -lfastrtps -lfastcdr
// Usage: fastdds_secure_listener ENCLAVE_DIR DOMAIN SECONDS [open]
// ("open": no security, to show that an open peer gets nothing).
// Not part of the test suite: the interop check of docs/ros.md, "Security".
// Prints one line per forecast received, then a summary line.
#include <fastcdr/Cdr.h>
#include <fastcdr/FastBuffer.h>
#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/domain/DomainParticipantListener.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/DataReaderListener.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>
#include <fastdds/dds/subscriber/qos/DataReaderQos.hpp>
#include <fastdds/dds/topic/TopicDataType.hpp>
#include <fastdds/dds/topic/TypeSupport.hpp>
#include <fastdds/rtps/transport/UDPv4TransportDescriptor.h>
#include <fastrtps/utils/IPLocator.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <string>
#include <thread>
#include <vector>

using namespace eprosima::fastdds::dds;
using eprosima::fastrtps::rtps::SerializedPayload_t;
using eprosima::fastrtps::rtps::InstanceHandle_t;

struct Forecast {
    std::vector<float> data;
};

class ForecastType : public TopicDataType {
public:
    ForecastType() {
        setName("std_msgs::msg::dds_::Float32MultiArray_");
        m_typeSize = 4096;
        m_isGetKeyDefined = false;
    }
    bool serialize(void*, SerializedPayload_t*) override { return false; }
    bool deserialize(SerializedPayload_t* payload, void* data) override {
        eprosima::fastcdr::FastBuffer fb(reinterpret_cast<char*>(payload->data), payload->length);
        eprosima::fastcdr::Cdr cdr(fb, eprosima::fastcdr::Cdr::DEFAULT_ENDIAN,
                                   eprosima::fastcdr::Cdr::DDS_CDR);
        try {
            cdr.read_encapsulation();
            uint32_t ndim = 0;
            cdr >> ndim;
            for (uint32_t i = 0; i < ndim; ++i) {
                std::string label;
                uint32_t size = 0, stride = 0;
                cdr >> label >> size >> stride;
            }
            uint32_t offset = 0;
            cdr >> offset;
            cdr >> static_cast<Forecast*>(data)->data;
        } catch (...) {
            return false;
        }
        return true;
    }
    std::function<uint32_t()> getSerializedSizeProvider(void*) override {
        return [] { return 4096u; };
    }
    void* createData() override { return new Forecast(); }
    void deleteData(void* d) override { delete static_cast<Forecast*>(d); }
    bool getKey(void*, InstanceHandle_t*, bool) override { return false; }
};

struct Listener : public DataReaderListener {
    std::atomic<int> received{0};
    std::atomic<int> matched{0};
    void on_data_available(DataReader* reader) override {
        Forecast f;
        SampleInfo info;
        while (reader->take_next_sample(&f, &info) == ReturnCode_t::RETCODE_OK) {
            if (!info.valid_data) continue;
            ++received;
            std::printf("forecast");
            for (float p : f.data) std::printf(" %.4f", p);
            std::printf("\n");
            std::fflush(stdout);
        }
    }
    void on_subscription_matched(DataReader*, const SubscriptionMatchedStatus& s) override {
        matched = s.current_count;
        std::printf("matched %d\n", s.current_count);
        std::fflush(stdout);
    }
};

struct ParticipantEvents : public DomainParticipantListener {
    void onParticipantAuthentication(DomainParticipant*,
                                       eprosima::fastrtps::rtps::ParticipantAuthenticationInfo&& info) override {
        std::printf("authentication %s\n",
                    info.status == eprosima::fastrtps::rtps::ParticipantAuthenticationInfo::AUTHORIZED_PARTICIPANT
                        ? "authorized"
                        : "unauthorized");
        std::fflush(stdout);
    }
};

int main(int argc, char** argv) {
    if (argc < 4) {
        std::fprintf(stderr, "usage: %s ENCLAVE_DIR DOMAIN SECONDS [open]\n", argv[0]);
        return 2;
    }
    std::string dir = argv[1];
    int domain = std::stoi(argv[2]);
    int seconds = std::stoi(argv[3]);
    bool open = argc > 4 && std::string(argv[4]) == "open";

    DomainParticipantQos pqos;
    pqos.name("fall_guard_monitor_fastdds");
    if (!open) {
        auto& p = pqos.properties().properties();
        p.emplace_back("dds.sec.auth.plugin", "builtin.PKI-DH");
        p.emplace_back("dds.sec.auth.builtin.PKI-DH.identity_ca", "file://" + dir + "/identity_ca.cert.pem");
        p.emplace_back("dds.sec.auth.builtin.PKI-DH.identity_certificate", "file://" + dir + "/cert.pem");
        p.emplace_back("dds.sec.auth.builtin.PKI-DH.private_key", "file://" + dir + "/key.pem");
        p.emplace_back("dds.sec.access.plugin", "builtin.Access-Permissions");
        p.emplace_back("dds.sec.access.builtin.Access-Permissions.permissions_ca",
                       "file://" + dir + "/permissions_ca.cert.pem");
        p.emplace_back("dds.sec.access.builtin.Access-Permissions.governance", "file://" + dir + "/governance.p7s");
        p.emplace_back("dds.sec.access.builtin.Access-Permissions.permissions", "file://" + dir + "/permissions.p7s");
        p.emplace_back("dds.sec.crypto.plugin", "builtin.AES-GCM-GMAC");
    }
    // Loopback only: UDPv4 on 127.0.0.1, unicast discovery to the
    // well-known ports of the first participants of the domain.
    auto udp = std::make_shared<eprosima::fastdds::rtps::UDPv4TransportDescriptor>();
    udp->interfaceWhiteList.push_back("127.0.0.1");
    pqos.transport().user_transports.push_back(udp);
    pqos.transport().use_builtin_transports = false;
    for (int pid = 0; pid < 8; ++pid) {
        eprosima::fastrtps::rtps::Locator_t loc;
        eprosima::fastrtps::rtps::IPLocator::setIPv4(loc, 127, 0, 0, 1);
        loc.port = 7400 + 250 * domain + 10 + 2 * pid;
        pqos.wire_protocol().builtin.initialPeersList.push_back(loc);
    }

    ParticipantEvents events;
    StatusMask mask = StatusMask::none();
    DomainParticipant* participant =
        DomainParticipantFactory::get_instance()->create_participant(domain, pqos, &events, mask);
    if (participant == nullptr) {
        std::printf("error: participant not created (security files?)\n");
        return 1;
    }
    TypeSupport type(new ForecastType());
    type.register_type(participant);
    Topic* topic = participant->create_topic("rt/fall_guard/forecast", type.get_type_name(), TOPIC_QOS_DEFAULT);
    Subscriber* sub = participant->create_subscriber(SUBSCRIBER_QOS_DEFAULT);
    DataReaderQos rqos = DATAREADER_QOS_DEFAULT;
    rqos.reliability().kind = RELIABLE_RELIABILITY_QOS;
    rqos.durability().kind = VOLATILE_DURABILITY_QOS;
    rqos.history().kind = KEEP_LAST_HISTORY_QOS;
    rqos.history().depth = 1;
    Listener listener;
    DataReader* reader = topic && sub ? sub->create_datareader(topic, rqos, &listener) : nullptr;
    if (reader == nullptr) {
        std::printf("error: reader not created (permissions?)\n");
        return 1;
    }
    std::printf("ready\n");
    std::fflush(stdout);
    std::this_thread::sleep_for(std::chrono::seconds(seconds));
    std::printf("summary received=%d matched=%d\n", listener.received.load(), listener.matched.load());
    participant->delete_contained_entities();
    DomainParticipantFactory::get_instance()->delete_participant(participant);
    return 0;
}
